// Taps that send the drone: a pixel of the AR picture (goto_pixel: the server finds the surface
// there) or a point of the map (goto, a standoff before the surface). A tapped target the
// server cannot reach (error unreachable_target with `nearest`) is retried at the nearest
// reachable point, once.

import { MapView } from "../views/map_view.js";

export class Taps {
  /** @param {{pilot: import("./pilot.js").Pilot, hud: import("./hud.js").Hud}} parts */
  constructor({ pilot, hud }) {
    this.pilot = pilot;
    this.hud = hud;
    this.commands = new Set(); // ids of goto commands from taps
  }

  /** Retry unreachable tapped targets; such an error is handled here (preventDefault): follow
   * the session state before the HUD does, which then does not show it. */
  follow(state) {
    state.addEventListener("error", (event) => {
      const error = event.detail;
      if (error.name !== "unreachable_target" || !error.nearest || !this.commands.has(error.command_id)) return;
      event.preventDefault();
      this.commands.delete(error.command_id);
      this.hud.toast("That point cannot be reached: flying to the nearest reachable point instead.", "warn");
      this.pilot.goto(error.nearest);
    });
  }

  /** A tap on the AR picture: pixel [u, v] of the colour image of frame `seq`. */
  ar(pixel, seq) {
    const id = this.pilot.gotoPixel(pixel.map((v) => Math.round(v * 10) / 10), seq);
    this.#sent(id, `fly to pixel ${pixel.map(Math.round).join(", ")}`);
  }

  /** A tap on the map: the point MapView picked. */
  map(picked) {
    const target = MapView.targetFor(picked);
    this.#sent(this.pilot.goto(target), `fly to ${target.map((v) => v.toFixed(2)).join(", ")} m`);
  }

  #sent(id, text) {
    if (id !== null) this.commands.add(id);
    this.hud.toast(id === null ? "not connected: tap ignored" : text, id === null ? "warn" : "info", 2000);
  }
}
