// The "Flights" dialog: the session's recorded flights (replay one over the map, or fly against
// its ghost), the ghost of the best flight during a new one, and the "share viewer link" button
// (a read-only link another phone opens to watch this session live).

import { bestFlight, FlightLibrary, FlightReplay, Ghost } from "../views/flight_replay.js";

const $ = (selector) => document.querySelector(selector);

function describe(f) {
  const parts = [`#${f.id}`, `${f.duration_s.toFixed(1)} s`, f.end ?? "in progress"];
  if (typeof f.result?.score === "number") parts.push(`score ${f.result.score}`);
  return parts.join(" · ");
}

export class FlightsPanel {
  /** @param {{client, map, hud, setView: (view: string) => void}} app */
  constructor(app) {
    this.app = app;
    this.library = new FlightLibrary(app.client);
    this.replay = new FlightReplay(app.map);
    this.ghost = new Ghost(app.map);
    this.flights = [];
    this.viewerLink = null;
    $("#btn-flights").addEventListener("click", () => this.open());
    $("#btn-share").addEventListener("click", () => this.share());
    $("#ghost-best").addEventListener("change", (e) => this.ghostOfBest(e.target.checked));
  }

  async open() {
    $("#flights").showModal();
    await this.refresh();
  }

  async refresh() {
    const status = $("#flights-status");
    try {
      this.flights = await this.library.list();
      status.textContent = this.flights.length ? "" : "no flight recorded yet: every flight is, from take-off to landing";
    } catch (exc) {
      this.flights = [];
      status.textContent = exc.message;
    }
    this.#render();
  }

  #render() {
    const list = $("#flight-list");
    list.replaceChildren();
    const best = bestFlight(this.flights);
    for (const f of [...this.flights].reverse()) {
      const item = document.createElement("li");
      item.dataset.flight = f.id;
      const label = document.createElement("span");
      label.textContent = describe(f) + (best?.id === f.id ? " · best" : "");
      const replay = document.createElement("button");
      replay.type = "button";
      replay.textContent = "Replay";
      replay.addEventListener("click", () => this.play(f.id));
      const ghost = document.createElement("button");
      ghost.type = "button";
      ghost.textContent = "Ghost";
      ghost.addEventListener("click", () => this.setGhost(f.id));
      item.append(label, replay, ghost);
      list.append(item);
    }
  }

  /** Replay a recorded flight over the map (the map view is shown). */
  async play(flightId, speed = 1) {
    try {
      const flight = await this.library.load(flightId);
      $("#flights").close();
      if (document.body.classList.contains("layout-ar")) this.app.setView("split");
      this.replay.play(flight, speed);
      this.app.hud.toast(`replaying flight #${flight.id} (${flight.duration_s.toFixed(1)} s)`, "info", 3000);
    } catch (exc) {
      this.app.hud.toast(exc.message, "error", 6000);
    }
  }

  /** Fly against a recorded flight: its ghost starts when the live drone's flight does. */
  async setGhost(flightId) {
    try {
      const flight = flightId === null ? null : await this.library.load(flightId);
      this.ghost.set(flight);
      if (flight) this.app.hud.toast(`ghost: flight #${flight.id}`, "info", 2500);
    } catch (exc) {
      this.app.hud.toast(exc.message, "error", 6000);
    }
  }

  async ghostOfBest(on) {
    if (!on) return this.setGhost(null);
    if (!this.flights.length) await this.refresh();
    const best = bestFlight(this.flights);
    if (best) await this.setGhost(best.id);
    else this.app.hud.toast("no recorded flight to race yet", "warn");
  }

  /** Ask the server for a viewer link and show it (copied to the clipboard when allowed). */
  async share() {
    const out = $("#viewer-link");
    try {
      const { id, token } = this.app.client.session ?? {};
      if (!id || !token) throw new Error("start a session first: the link watches it");
      const response = await fetch(`/api/sessions/${id}/viewers`, { method: "POST", headers: { Authorization: `Bearer ${token}` } });
      const body = await response.json();
      if (!response.ok) throw new Error(body?.error?.message ?? `HTTP ${response.status}`);
      this.viewerLink = body;
      out.value = body.url;
      out.hidden = false;
      out.select();
      navigator.clipboard?.writeText(body.url).catch(() => {});
    } catch (exc) {
      out.hidden = true;
      this.app.hud.toast(`no viewer link: ${exc.message}`, "error", 6000);
    }
  }

  /** The ghost starts and stops with the session state's drone (session/state.js). */
  follow(state) {
    state.addEventListener("drone", ({ detail }) => this.ghost.droneState(detail));
  }

  tick(now) {
    this.replay.tick(now);
  }

  snapshot() {
    const pose = (marker) => (marker.pose ? { position: marker.pose.position, mode: marker.pose.mode } : null);
    return {
      flights: this.flights,
      replay: { playing: this.replay.playing, elapsed: this.replay.elapsed, flight: this.replay.marker.flight?.id ?? null, pose: pose(this.replay.marker) },
      ghost: { flight: this.ghost.flight?.id ?? null, pose: pose(this.ghost.marker) },
      viewerLink: this.viewerLink?.url ?? null,
    };
  }
}
