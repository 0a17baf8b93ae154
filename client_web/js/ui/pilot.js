// The pilot's commands: fly to a tapped pixel or map point, fly by two sticks (mode 2: left
// stick throttle and yaw, right stick pitch and roll), take off, hold, land, and the flight mode
// (what the sticks mean: position, angle or acro; PROTOCOL.md "Flight modes"). In position mode
// sticks go out at STICK_HZ while a stick is held (the server centres sticks older than
// stick_timeout_s), then zeros once on release. In angle and acro centred sticks mean something
// too (level, or keep the attitude), so they go out all the time while connected, until
// IDLE_STREAM_MS after the sticks were last touched: stale sticks there hand the drone back to
// position mode's braking and holding (an abandoned page does not keep its session busy).

import { Joystick } from "./joystick.js";

export const STICK_HZ = 15;
export const FLIGHT_MODES = ["position", "angle", "acro"];
const MODE_CONFIRM_MS = 3000; // a mode asked for waits this long for drone_state to report it
const IDLE_STREAM_MS = 30000; // angle and acro: centred sticks stream this long after a touch

export class Pilot extends EventTarget {
  /**
   * @param {import("../network/connection.js").SessionClient} client
   * @param {{left: HTMLElement, right: HTMLElement, modes?: HTMLElement}} controls the two
   *   joystick elements, and the mode switch: buttons with data-flight-mode inside `modes`
   */
  constructor(client, { left, right, modes }) {
    super();
    this.client = client;
    this.log = []; // commands sent: {id, name, fields, at}
    this.left = new Joystick(left, { onChange: () => this.#sticksChanged(true) });
    this.right = new Joystick(right, { onChange: () => this.#sticksChanged(true) });
    this.timer = null;
    this.touchedAt = performance.now();
    this.flightMode = "position"; // as asked here, or as the server last reported it
    this.asked = null; // {mode, at}: a flight_mode command not yet confirmed by drone_state
    this.modeButtons = modes ? [...modes.querySelectorAll("[data-flight-mode]")] : [];
    for (const button of this.modeButtons) {
      button.addEventListener("click", () => this.setFlightMode(button.dataset.flightMode));
    }
    this.#showMode();
  }

  /** [throttle, yaw, pitch, roll] in -1..1; yaw positive turns left (counter-clockwise). */
  get sticks() {
    const l = this.left.value;
    const r = this.right.value;
    return [l.y, -l.x, r.y, r.x].map((v) => Math.max(-1, Math.min(1, v)) || 0);
  }

  #send(name, fields = {}) {
    let id = null;
    try {
      id = this.client.command(name, fields);
    } catch (exc) {
      this.dispatchEvent(new CustomEvent("refused", { detail: { name, message: exc.message } }));
      return null;
    }
    if (id !== null) {
      this.log.push({ id, name, fields, at: performance.now() });
      if (this.log.length > 200) this.log.shift();
      this.dispatchEvent(new CustomEvent("sent", { detail: { id, name, fields } }));
    }
    return id;
  }

  #tick() {
    const held = this.left.active || this.right.active;
    if (!held && performance.now() - this.touchedAt > IDLE_STREAM_MS) {
      clearInterval(this.timer); // untouched for long: let the server brake and hold
      this.timer = null;
      return;
    }
    // Centred sticks streamed in angle or acro go out only on an open socket: they must never
    // wake the connection or take the session back from another tab.
    if (held || this.client.isOpen) this.#send("sticks", { sticks: this.sticks });
  }

  #sticksChanged(touched = false) {
    if (touched) this.touchedAt = performance.now();
    const stream = this.left.active || this.right.active || this.flightMode !== "position";
    if (stream && this.timer === null) {
      this.#tick();
      this.timer = setInterval(() => this.#tick(), 1000 / STICK_HZ);
    } else if (!stream && this.timer !== null) {
      clearInterval(this.timer);
      this.timer = null;
      this.#send("sticks", { sticks: [0, 0, 0, 0] });
    }
  }

  /** Ask for a flight mode: "position", "angle" or "acro". */
  setFlightMode(mode) {
    if (!FLIGHT_MODES.includes(mode)) throw new Error(`unknown flight mode ${mode}`);
    const id = this.#send("flight_mode", { flight_mode: mode });
    if (id === null) return null;
    this.asked = { mode, at: performance.now() };
    this.#adopt(mode);
    return id;
  }

  /** Take the flight mode the session state's drone reports (session/state.js). */
  follow(state) {
    state.addEventListener("drone", ({ detail }) => this.serverMode(detail.flight_mode));
  }

  /** The mode drone_state reports: the server's word wins (a reload, another device), except
   * while a mode asked here is on its way. */
  serverMode(mode) {
    if (!FLIGHT_MODES.includes(mode)) return;
    if (this.asked && (this.asked.mode === mode || performance.now() - this.asked.at > MODE_CONFIRM_MS)) {
      this.asked = null;
    }
    if (!this.asked && mode !== this.flightMode) this.#adopt(mode);
  }

  #adopt(mode) {
    this.flightMode = mode;
    this.#showMode();
    this.#sticksChanged(true);
    this.dispatchEvent(new CustomEvent("flightmode", { detail: { mode } }));
  }

  #showMode() {
    for (const button of this.modeButtons) {
      button.setAttribute("aria-pressed", String(button.dataset.flightMode === this.flightMode));
    }
  }

  /** Fly to the 3D point seen at pixel [u, v] of the colour image of frame seq. */
  gotoPixel(pixel, seq) {
    return this.#send("goto_pixel", { pixel, seq });
  }

  /** Fly to a world point [x, y, z], metres. */
  goto(target) {
    return this.#send("goto", { target });
  }

  takeoff() {
    return this.#send("takeoff");
  }

  hold() {
    return this.#send("hold");
  }

  land() {
    return this.#send("land");
  }
}
