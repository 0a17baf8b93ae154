// Heads-up line, banner and toasts: tracking, fps, latency, dropped frames, drone mode and
// clearance, connection state, collision warnings and errors with their message.

const FPS_WINDOW_MS = 2000;
const CLEARANCE_WARN_M = 0.3;
const CLEARANCE_BAD_M = 0.15;

// While tracking recovers (PROTOCOL.md, "Tracking recovery"): how, said beside the state.
const RECOVERY = Object.freeze({ relocalised: "found again", segment: "placed roughly", merged: "back in the map" });

export class Hud {
  constructor(root = document) {
    this.fields = Object.fromEntries([...root.querySelectorAll("[data-field]")].map((el) => [el.dataset.field, el]));
    this.banner = root.querySelector("#banner");
    this.toasts = root.querySelector("#toasts");
    this.poseTimes = [];
    // Banner and toasts sit just below the HUD, whose height changes with the screen.
    const hud = root.querySelector("#hud");
    new ResizeObserver(() => document.documentElement.style.setProperty("--hud-h", `${hud.offsetHeight}px`)).observe(hud);
  }

  #set(name, text, state) {
    const el = this.fields[name];
    if (!el) return;
    if (el.textContent !== text) el.textContent = text;
    if (state !== undefined) el.dataset.state = state;
  }

  connection(state, message) {
    const label = { idle: "offline", connecting: "connecting…", open: "connected", reconnecting: "reconnecting…",
      paused: "paused", ended: "session ended", taken_over: "taken over" }[state] ?? state;
    this.#set("connection", label, state);
    this.fields.connection.title = message || label;
  }

  pose(pose) {
    const now = performance.now();
    this.poseTimes.push(now);
    while (this.poseTimes.length && this.poseTimes[0] < now - FPS_WINDOW_MS) this.poseTimes.shift();
    const how = RECOVERY[pose.recovery];
    this.#set("tracking", how ? `tracking ${pose.state} · ${how}` : `tracking ${pose.state}`, pose.state);
    this.#failures(pose.failures ?? {});
  }

  /** The server's failure counts for this session (pose.failures): shown once any is above 0. */
  #failures(counts) {
    const el = this.fields.failures;
    const failed = Object.entries(counts).filter(([, n]) => n > 0);
    if (!el || (el.hidden && failed.length === 0)) return;
    const total = failed.reduce((sum, [, n]) => sum + n, 0);
    el.hidden = failed.length === 0;
    this.#set("failures", `fail ${total}`);
    el.title = failed.map(([name, n]) => `${name}: ${n}`).join(", ");
  }

  /** A replay waiting for the server (it slows down rather than drop frames): say so. */
  heldBack(held) {
    const el = this.fields.held;
    if (el) el.hidden = !held;
  }

  /** fps from the poses of the last two seconds; latency median in ms; dropped both sides. */
  rates({ latencyMs, clientSkipped, serverDropped }) {
    const now = performance.now();
    while (this.poseTimes.length && this.poseTimes[0] < now - FPS_WINDOW_MS) this.poseTimes.shift();
    const fps = (this.poseTimes.length * 1000) / FPS_WINDOW_MS;
    this.#set("fps", `${fps.toFixed(1)} fps`);
    this.#set("latency", Number.isFinite(latencyMs) ? `${Math.round(latencyMs)} ms` : "— ms");
    this.#set("dropped", `drop ${clientSkipped}+${serverDropped}`);
  }

  drone(state) {
    if (!state) {
      this.#set("drone", "drone —", "none");
      this.#set("clearance", "clear —", "none");
      this.#set("flight-mode", "sticks —", "none");
      return;
    }
    const flying = ["manual", "goto", "hover", "landing"].includes(state.mode);
    this.#set("drone", `drone ${state.mode}`, state.mode === "crashed" ? "bad" : flying ? "flying" : "none");
    if (state.flight_mode) this.#set("flight-mode", `sticks ${state.flight_mode}`, state.flight_mode === "position" ? "none" : "warn");
    if (state.clearance === undefined) {
      this.#set("clearance", "clear —", "none");
    } else {
      const c = state.clearance;
      this.#set("clearance", `clear ${c.toFixed(2)} m`, c < CLEARANCE_BAD_M ? "bad" : c < CLEARANCE_WARN_M ? "warn" : "none");
    }
  }

  points(total) {
    this.#set("points", `map ${total >= 10000 ? `${Math.round(total / 1000)}k` : total}`);
  }

  /** A banner that stays `ms` milliseconds (collisions, connection loss). */
  showBanner(text, kind = "error", ms = 4000) {
    this.banner.textContent = text;
    this.banner.dataset.kind = kind;
    this.banner.hidden = false;
    clearTimeout(this.bannerTimer);
    if (ms > 0) this.bannerTimer = setTimeout(() => (this.banner.hidden = true), ms);
  }

  hideBanner() {
    this.banner.hidden = true;
  }

  toast(text, kind = "info", ms = 4500) {
    const el = document.createElement("div");
    el.className = "toast";
    el.dataset.kind = kind;
    el.textContent = text;
    this.toasts.append(el);
    while (this.toasts.children.length > 4) this.toasts.firstElementChild.remove();
    setTimeout(() => el.remove(), ms);
  }
}
