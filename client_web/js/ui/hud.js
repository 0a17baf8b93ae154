// Heads-up line, banner and toasts: tracking, fps, latency, dropped frames, what a stream that
// runs behind its rate waits for (server, page or network, from measured times: network/page_load.js),
// drone mode and clearance, connection state, collision warnings and errors with their message.

import { State } from "../network/connection.js";
import { mean, waitsFor } from "../network/page_load.js";

const FPS_WINDOW_MS = 2000;
const BEHIND = 0.85; // poses per second under this share of the asked rate: the stream is behind
const WAITS_EVERY_MS = 1000; // the "waits for" chip changes at most this often (no flicker)
const WAITS_CHECKS = 2; // checks in a row that agree before it shows or hides
const CLEARANCE_WARN_M = 0.3;
const CLEARANCE_BAD_M = 0.15;

// While tracking recovers (PROTOCOL.md, "Tracking recovery"): how, said beside the state.
const RECOVERY = Object.freeze({ relocalised: "found again", segment: "placed roughly", merged: "back in the map" });
const EVENT_KINDS = Object.freeze({ spawned: "ok", arrived: "ok", landed: "info", replanned: "info", blocked: "warn",
  collision: "warn", crash: "error", restarted: "ok" });
const COURSE_EVENTS = new Set(["gate_passed", "gate_missed", "course_finished"]); // views/course_view.js shows them

export class Hud {
  constructor(root = document) {
    this.fields = Object.fromEntries([...root.querySelectorAll("[data-field]")].map((el) => [el.dataset.field, el]));
    this.banner = root.querySelector("#banner");
    this.toasts = root.querySelector("#toasts");
    this.poseTimes = [];
    this.frameTimes = []; // [at, server_total ms, round trip ms] of the poses in the window
    this.waits = { shown: false, agree: 0, checkedAt: 0, last: null };
    // Banner and toasts sit just below the HUD, whose height changes with the screen.
    const hud = root.querySelector("#hud");
    new ResizeObserver(() => document.documentElement.style.setProperty("--hud-h", `${hud.offsetHeight}px`)).observe(hud);
  }

  /** Show what the session state says (session/state.js): the connection, poses, the map's
   * size, the drone, its events, loop closures and the server's errors. An error a listener
   * before this one handled (preventDefault) is not shown. */
  follow(state) {
    state.addEventListener("status", ({ detail }) => this.#status(detail));
    state.addEventListener("pose", ({ detail: pose }) => this.pose(pose, state.lastLatencyMs));
    state.addEventListener("map", ({ detail }) => this.points(detail.total));
    state.addEventListener("drone", ({ detail }) => this.drone(detail));
    state.addEventListener("reset", () => this.drone(null));
    state.addEventListener("drone_event", ({ detail }) => this.#droneEvent(detail));
    state.addEventListener("corrected", ({ detail: c }) => {
      const shift = Math.hypot(c.T_correction[3], c.T_correction[7], c.T_correction[11]);
      this.toast(`loop closed (${c.loops}): map corrected by ${(100 * shift).toFixed(1)} cm here`, "ok", 5000);
    });
    state.addEventListener("error", (event) => {
      if (event.defaultPrevented) return;
      const error = event.detail;
      const text = `${error.name} (${error.code}): ${error.message}`;
      if (error.fatal) this.showBanner(text, "error", 10000);
      else this.toast(text, "error", 6000);
    });
  }

  #status({ state, message }) {
    this.connection(state, message);
    const banners = {
      [State.RECONNECTING]: [`Connection lost: ${message}`, "warn"],
      [State.TAKEN_OVER]: ["Another tab or device took this session over. Start takes it back.", "warn"],
      [State.ENDED]: [`${message}. Start again for a new session.`, "error"],
    };
    if (state in banners) this.showBanner(...banners[state], 0); // until the state changes
    else if (state === State.OPEN) this.hideBanner();
  }

  #droneEvent(event) {
    if (COURSE_EVENTS.has(event.event)) return;
    const where = event.position.map((v) => v.toFixed(2)).join(", ");
    if (event.event === "crash") this.showBanner(`Crash! ${event.message} (at ${where} m)`, "error", 6000);
    else if (event.event === "collision") this.showBanner(`Bump! ${event.message} (at ${where} m)`, "warn", 3000);
    else if (event.event === "blocked") this.showBanner(`Route blocked: ${event.message}`, "warn", 4000);
    else if (event.event === "restarted") this.showBanner(`Back in the race: ${event.message}`, "ok", 3000);
    this.toast(`${event.event}: ${event.message}`, EVENT_KINDS[event.event] ?? "info");
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

  /** A pose came back, latencyMs after its frame went out (NaN when not measured). */
  pose(pose, latencyMs = NaN) {
    const now = performance.now();
    this.poseTimes.push(now);
    while (this.poseTimes.length && this.poseTimes[0] < now - FPS_WINDOW_MS) this.poseTimes.shift();
    const serverMs = pose.timings_ms?.server_total;
    if (Number.isFinite(serverMs) && Number.isFinite(latencyMs)) this.frameTimes.push([now, serverMs, latencyMs]);
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

  /** fps from the poses of the last two seconds; latency median in ms; dropped both sides; and,
   * while streaming at `askedFps` (load: the page's PageLoad summary), what the stream waits
   * for when it runs behind. Returns that (waitsFor's answer) or null while it keeps up. */
  rates({ latencyMs, clientSkipped, serverDropped, askedFps = 0, load = null }) {
    const now = performance.now();
    while (this.poseTimes.length && this.poseTimes[0] < now - FPS_WINDOW_MS) this.poseTimes.shift();
    const fps = (this.poseTimes.length * 1000) / FPS_WINDOW_MS;
    this.#set("fps", `${fps.toFixed(1)} fps`);
    this.#set("latency", Number.isFinite(latencyMs) ? `${Math.round(latencyMs)} ms` : "— ms");
    this.#set("dropped", `drop ${clientSkipped}+${serverDropped}`);
    if (now - this.waits.checkedAt >= WAITS_EVERY_MS) {
      this.waits.checkedAt = now;
      // Means over the window's frames: the period between frames is the mean round trip plus
      // the page's gap, and a slow frame's tail belongs to the round trip, not to the page.
      while (this.frameTimes.length && this.frameTimes[0][0] < now - FPS_WINDOW_MS) this.frameTimes.shift();
      const frames = this.frameTimes;
      const behind = askedFps > 0 && fps > 0 && fps < BEHIND * askedFps && frames.length > 0;
      this.#waits(behind ? waitsFor({ periodMs: 1000 / fps, latencyMs: mean(frames.map((f) => f[2])),
        serverMs: mean(frames.map((f) => f[1])), busyFraction: load?.fraction ?? 0 }) : null, load);
    }
    return this.waits.shown ? this.waits.last : null;
  }

  /** Show or hide the "waits for" chip once WAITS_CHECKS checks in a row agree. */
  #waits(behind, load) {
    const el = this.fields.held;
    if (behind) this.waits.last = behind;
    this.waits.agree = (behind !== null) === this.waits.shown ? 0 : this.waits.agree + 1;
    if (this.waits.agree >= WAITS_CHECKS) {
      this.waits.shown = behind !== null;
      this.waits.agree = 0;
    }
    if (!el) return;
    el.hidden = !this.waits.shown;
    const w = this.waits.last;
    if (!this.waits.shown || !w) return;
    const ms = (v) => `${Math.round(v)} ms`;
    const text = { server: `waiting for server ${ms(w.server)}`, network: `waiting for network ${ms(w.network)}`,
      page: `page busy${load?.top ? `: ${load.top}` : ""} ${ms(w.page)}` }[w.name];
    this.#set("held", text, w.name === "server" ? "warn" : "bad");
    el.dataset.waitsFor = w.name;
    el.title = `the stream runs slower than asked; per frame: server ${ms(w.server)}, page ${ms(w.page)},` +
      ` network ${ms(w.network)}`;
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
