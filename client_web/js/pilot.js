// The pilot's commands: fly to a tapped pixel or map point, fly by two sticks (mode 2: left
// stick throttle and yaw, right stick pitch and roll), take off, hold, land. Sticks go out at
// STICK_HZ while a stick is held (the server centres sticks older than stick_timeout_s), then
// zeros once on release.

import { Joystick } from "./joystick.js";

export const STICK_HZ = 15;

export class Pilot extends EventTarget {
  /**
   * @param {import("./connection.js").SessionClient} client
   * @param {{left: HTMLElement, right: HTMLElement}} sticks the two joystick elements
   */
  constructor(client, { left, right }) {
    super();
    this.client = client;
    this.log = []; // commands sent: {id, name, fields, at}
    this.left = new Joystick(left, { onChange: () => this.#sticksChanged() });
    this.right = new Joystick(right, { onChange: () => this.#sticksChanged() });
    this.timer = null;
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

  #sticksChanged() {
    const held = this.left.active || this.right.active;
    if (held && this.timer === null) {
      this.#send("sticks", { sticks: this.sticks });
      this.timer = setInterval(() => this.#send("sticks", { sticks: this.sticks }), 1000 / STICK_HZ);
    } else if (!held && this.timer !== null) {
      clearInterval(this.timer);
      this.timer = null;
      this.#send("sticks", { sticks: [0, 0, 0, 0] });
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
