// An on-screen joystick for touch, pen and mouse (pointer events, one pointer per stick, so two
// thumbs fly at once). The value is x, y in -1..1 (x right, y up), back to 0 on release.

const DEAD_ZONE = 0.06;

export class Joystick {
  /**
   * @param {HTMLElement} element a square-ish element; its child ".knob" follows the pointer
   * @param {{onChange?: (value: {x: number, y: number, active: boolean}) => void}} options
   */
  constructor(element, { onChange } = {}) {
    this.element = element;
    this.knob = element.querySelector(".knob");
    this.onChange = onChange;
    this.value = { x: 0, y: 0, active: false };
    this.pointerId = null;
    element.addEventListener("pointerdown", (e) => this.#down(e));
    element.addEventListener("pointermove", (e) => this.#move(e));
    for (const type of ["pointerup", "pointercancel", "lostpointercapture"]) {
      element.addEventListener(type, (e) => this.#up(e));
    }
  }

  get active() {
    return this.value.active;
  }

  #down(e) {
    if (this.pointerId !== null) return;
    e.preventDefault();
    this.pointerId = e.pointerId;
    try {
      this.element.setPointerCapture(e.pointerId);
    } catch {
      /* synthetic events have no capture */
    }
    this.element.classList.add("held");
    this.#set(e, true);
  }

  #move(e) {
    if (e.pointerId !== this.pointerId) return;
    e.preventDefault();
    this.#set(e, true);
  }

  #up(e) {
    if (e.pointerId !== this.pointerId) return;
    this.pointerId = null;
    this.element.classList.remove("held");
    this.value = { x: 0, y: 0, active: false };
    this.knob.style.transform = "translate(-50%, -50%)";
    this.onChange?.(this.value);
  }

  #set(e, active) {
    const rect = this.element.getBoundingClientRect();
    const radius = rect.width / 2;
    let dx = (e.clientX - (rect.left + radius)) / radius;
    let dy = (e.clientY - (rect.top + rect.height / 2)) / radius;
    const length = Math.hypot(dx, dy);
    if (length > 1) [dx, dy] = [dx / length, dy / length];
    const shape = (v) => (Math.abs(v) < DEAD_ZONE ? 0 : Math.round(v * 1000) / 1000);
    this.value = { x: shape(dx), y: shape(-dy), active };
    this.knob.style.transform = `translate(calc(-50% + ${dx * radius * 0.8}px), calc(-50% + ${dy * radius * 0.8}px))`;
    this.onChange?.(this.value);
  }
}
