// The "Flights" dialog: the session's recorded flights (replay one over the map, or fly against
// its ghost), the ghost of the best flight during a new one, its shared room's races (the room's
// best list, and each race this session flew in, replayed with every pilot's drone at once:
// views/race_replay.js), and the "share viewer link" button (a read-only link another phone
// opens to watch this session live).

import { bestFlight, FlightLibrary, FlightReplay, Ghost } from "../views/flight_replay.js";
import { RaceReplay } from "../views/race_replay.js";
import { pilotColour } from "../views/room_pilots.js";

const $ = (selector) => document.querySelector(selector);
const hex = (colour) => `#${colour.toString(16).padStart(6, "0")}`;
const plural = (n, word) => `${n} ${word}${n === 1 ? "" : word.endsWith("sh") ? "es" : "s"}`;

function describe(f) {
  const parts = [`#${f.id}`, `${f.duration_s.toFixed(1)} s`, f.end ?? "in progress"];
  if (typeof f.result?.score === "number") parts.push(`score ${f.result.score}`);
  return parts.join(" · ");
}

/** A best-list entry (RaceBestEntry): "alice · 4.2 s · 0 missed · 1 crash · easy · race 3". */
function describeBest(e) {
  return [e.pilot || "(no name)", `${e.time_s.toFixed(1)} s`, `${e.missed} missed`, plural(e.crashes, "crash"),
    e.difficulty, `race ${e.race}`].join(" · ");
}

/** A race pilot (RacePilot): "#1 alice 4.2 s", or "bob 2/3 gates" when it did not finish. */
function describePilot(p, gates) {
  const name = p.name || "(no name)";
  if (!p.finished) return `${name} ${p.passed}/${gates} gates, did not finish`;
  const extra = [p.missed ? `${p.missed} missed` : "", p.crashes ? plural(p.crashes, "crash") : ""].filter(Boolean);
  return `${p.rank ? `#${p.rank} ` : ""}${name} ${p.time_s.toFixed(1)} s${extra.length ? ` (${extra.join(", ")})` : ""}`;
}

export class FlightsPanel {
  /** @param {{client, map, hud, setView: (view: string) => void}} app */
  constructor(app) {
    this.app = app;
    this.library = new FlightLibrary(app.client);
    this.replay = new FlightReplay(app.map);
    this.raceReplay = new RaceReplay(app.map, { onStop: (ended) => ended && this.#raceReplayEnded() });
    this.ghost = new Ghost(app.map);
    this.flights = [];
    this.races = []; // the races this session flew in (RaceRecord), oldest first
    this.best = []; // its room's best list (RaceBestEntry)
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
    const races = this.library.races().catch(() => ({ races: [], best: [] })); // none: the part hides
    try {
      this.flights = await this.library.list();
      status.textContent = this.flights.length ? "" : "no flight recorded yet: every flight is, from take-off to landing";
    } catch (exc) {
      this.flights = [];
      status.textContent = exc.message;
    }
    this.#render();
    ({ races: this.races, best: this.best } = await races);
    this.#renderRaces();
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

  /** The Races part, shown when the session has races or its room a best list: the best list,
   * and each race (newest first) with its pilots, each in its drone's colour, and "Replay
   * together". */
  #renderRaces() {
    $("#races").hidden = !this.races.length && !this.best.length;
    $("#race-best-title").hidden = !this.best.length;
    $("#race-best").replaceChildren(...this.best.map((e, i) => {
      const item = document.createElement("li");
      item.dataset.session = e.session;
      item.textContent = `${i + 1}. ${describeBest(e)}`;
      return item;
    }));
    $("#race-list").replaceChildren(...[...this.races].reverse().map((race) => {
      const item = document.createElement("li");
      item.dataset.race = String(race.number);
      const gates = race.gates.length / 7;
      const label = document.createElement("span");
      label.append(`Race ${race.number} (${race.difficulty}, ${gates} gates): `);
      const order = [...race.pilots.keys()].sort((a, b) =>
        (race.pilots[a].rank || Infinity) - (race.pilots[b].rank || Infinity) || a - b);
      order.forEach((index, k) => {
        const pilot = document.createElement("b");
        pilot.className = "race-pilot";
        pilot.dataset.pilot = String(index);
        pilot.style.color = hex(pilotColour(index)); // its drone's colour in the replay
        pilot.textContent = describePilot(race.pilots[index], gates);
        label.append(...(k ? [" · ", pilot] : [pilot]));
      });
      const replay = document.createElement("button");
      replay.type = "button";
      replay.textContent = "Replay together";
      replay.addEventListener("click", () => this.playRace(race.number));
      item.append(label, replay);
      return item;
    }));
  }

  /** Replay race `number` over the map: every pilot's drone at once (the map view is shown). */
  async playRace(number, speed = 1) {
    try {
      const data = await this.library.raceFlights(number);
      $("#flights").close();
      const view = document.body.classList;
      if (view.contains("layout-ar") || view.contains("layout-fpv")) this.app.setView("map");
      this.replay.stop();
      this.raceReplay.play(data, speed);
      const length = data.race.ended_at - data.race.started_at;
      this.app.hud.toast(`replaying race ${number} (${length.toFixed(1)} s, ${data.pilots.length} pilots)`, "info", 3000);
    } catch (exc) {
      this.app.hud.toast(exc.message, "error", 6000);
    }
  }

  #raceReplayEnded() {
    this.app.hud.toast(`race ${this.raceReplay.race.number} replayed`, "info", 2500);
  }

  /** Replay a recorded flight over the map (the map view is shown). */
  async play(flightId, speed = 1) {
    try {
      const flight = await this.library.load(flightId);
      $("#flights").close();
      if (document.body.classList.contains("layout-ar")) this.app.setView("split");
      this.raceReplay.stop();
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
    this.raceReplay.tick(now);
  }

  snapshot() {
    const pose = (marker) => (marker.pose ? { position: marker.pose.position, mode: marker.pose.mode } : null);
    return {
      flights: this.flights,
      replay: { playing: this.replay.playing, elapsed: this.replay.elapsed, flight: this.replay.marker.flight?.id ?? null, pose: pose(this.replay.marker) },
      ghost: { flight: this.ghost.flight?.id ?? null, pose: pose(this.ghost.marker) },
      viewerLink: this.viewerLink?.url ?? null,
      races: { shown: !$("#races").hidden, list: this.races, best: this.best,
        listed: [...document.querySelectorAll("#race-list li > span")].map((el) => el.textContent),
        bestListed: [...document.querySelectorAll("#race-best li")].map((el) => el.textContent) },
      raceReplay: this.raceReplay.snapshot(),
    };
  }
}
