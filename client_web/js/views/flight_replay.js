// Recorded flights on the map view: the session's flights (and its shared room's races) over
// REST, a flight's pose at any time (states interpolated), a replay of one flight or of several
// drones' flights at once on one wall clock (a race: views/race_replay.js), and a translucent
// "ghost" of a chosen (or the best) flight flying beside the live drone during a new flight. A
// flight is the JSON of GET /api/sessions/{id}/flights/{flight_id}.json (shared/PROTOCOL.md,
// "Flight recordings"): rows of state_columns (t s, x y z m and vx vy vz m/s in the world frame,
// qx qy qz qw, mode); its rows happened at wall clock started_at + t - start_time_s (Unix s).

import * as THREE from "three";
import { createDrone } from "./drone_model.js";

const GROUNDED = new Set(["landed", "faulted"]);

/** The session's recorded flights and their JSON, with the owner's token. */
export class FlightLibrary {
  constructor(client, { baseUrl = window.location.origin } = {}) {
    this.client = client;
    this.baseUrl = baseUrl;
    this.cache = new Map(); // finished flights do not change: id -> flight
  }

  async #get(path) {
    const { id, token } = this.client.session ?? {};
    if (!id || !token) throw new Error("no session of yours yet: start one to record flights");
    const response = await fetch(`${this.baseUrl}/api/sessions/${id}/${path}`, { headers: { Authorization: `Bearer ${token}` } });
    const body = await response.json().catch(() => null);
    if (!response.ok) throw new Error(`${path}: HTTP ${response.status} ${body?.error?.message ?? ""}`);
    return body;
  }

  /** Summaries, oldest first: {id, started_at, duration_s, finished, end, result, ...}. */
  async list() {
    return (await this.#get("flights")).flights;
  }

  async load(flightId) {
    if (this.cache.has(flightId)) return this.cache.get(flightId);
    const flight = await this.#get(`flights/${encodeURIComponent(flightId)}.json`);
    if (flight.finished) this.cache.set(flightId, flight);
    return flight;
  }

  /** The shared-room races this session flew in and its room's best list: {races, best}. */
  async races() {
    return this.#get("races");
  }

  /** Every pilot's flights of race `number`: {race, pilots: [{session, name, flights}]}. */
  async raceFlights(number) {
    return this.#get(`races/${encodeURIComponent(number)}/flights`);
  }
}

/** The best of a list of flight summaries: the best course score when any flight has one,
 * else the longest flight; null for an empty list. */
export function bestFlight(flights) {
  const scored = flights.filter((f) => typeof f.result?.score === "number");
  const pool = scored.length ? scored : flights;
  const key = scored.length ? (f) => f.result.score : (f) => f.duration_s;
  return pool.reduce((best, f) => (best === null || key(f) > key(best) ? f : best), null);
}

/** The flight's pose `elapsed` seconds after its start: {position [x,y,z], quaternion
 * [x,y,z,w], mode}, interpolated between the two rows around it (clamped to the ends). */
export function poseAt(flight, elapsed) {
  const rows = flight.states;
  if (!rows.length) return null;
  const c = Object.fromEntries(flight.state_columns.map((name, i) => [name, i]));
  const t = flight.start_time_s + elapsed;
  let lo = 0;
  let hi = rows.length - 1;
  if (t <= rows[0][c.t]) hi = 0;
  else if (t >= rows[hi][c.t]) lo = hi;
  while (hi - lo > 1) {
    const mid = (lo + hi) >> 1;
    if (rows[mid][c.t] <= t) lo = mid;
    else hi = mid;
  }
  const a = rows[lo];
  const b = rows[hi];
  const span = b[c.t] - a[c.t];
  const w = span > 0 ? Math.min(1, Math.max(0, (t - a[c.t]) / span)) : 0;
  const position = ["x", "y", "z"].map((k) => a[c[k]] + w * (b[c[k]] - a[c[k]]));
  const qa = new THREE.Quaternion(a[c.qx], a[c.qy], a[c.qz], a[c.qw]);
  const qb = new THREE.Quaternion(b[c.qx], b[c.qy], b[c.qz], b[c.qw]);
  const q = qa.slerp(qb, w);
  return { position, quaternion: [q.x, q.y, q.z, q.w], mode: (w < 0.5 ? a : b)[c.mode] };
}

/** Of a drone's flights (each with started_at, Unix seconds), the one to show at wall clock
 * `wall` and the time into it: the latest one opened by then (clamped to its end once it
 * closed: the drone stays where it landed), else the first (at its start); null for none. */
export function flightAt(flights, wall) {
  let chosen = null;
  for (const f of flights) {
    if ((f.started_at ?? 0) <= wall && (chosen === null || f.started_at >= chosen.started_at)) chosen = f;
  }
  chosen ??= flights.reduce((first, f) => (first === null || f.started_at < first.started_at ? f : first), null);
  return chosen && { flight: chosen, elapsed: wall - (chosen.started_at ?? 0) };
}

/** A drone and its recorded path, drawn in a MapView's scene: translucent in one colour (a
 * ghost, the replayed flight), or with `paint` ({colour, emissive}: drone_model.js) an opaque
 * drone in that paint (a pilot of a replayed race). path: false draws no path. */
export class FlightMarker {
  constructor(mapView, { colour = 0x4dd0e1, opacity = 0.45, name = "ghost", paint = null, path = true } = {}) {
    this.map = mapView;
    this.drone = createDrone(paint ?? undefined);
    this.drone.name = name;
    if (!paint) {
      this.drone.traverse((o) => {
        if (!o.material) return;
        o.material = o.material.clone();
        o.material.color?.setHex(colour);
        o.material.emissive?.setHex(0x000000);
        o.material.transparent = true;
        o.material.opacity = opacity;
        o.material.depthWrite = false;
      });
    }
    this.drone.visible = false;
    this.drawsPath = path;
    this.path = new THREE.Line(new THREE.BufferGeometry(), new THREE.LineBasicMaterial({ color: paint?.colour ?? colour, transparent: true, opacity: 0.6 }));
    this.path.frustumCulled = false;
    this.path.visible = false;
    mapView.scene.add(this.drone, this.path);
    this.flight = null;
    this.pose = null;
  }

  show(flight) {
    this.flight = flight;
    this.path.geometry.dispose();
    if (this.drawsPath) {
      const c = Object.fromEntries(flight.state_columns.map((name, i) => [name, i]));
      const points = flight.states.map((r) => new THREE.Vector3(r[c.x], r[c.y], r[c.z]));
      this.path.geometry = new THREE.BufferGeometry().setFromPoints(points);
      this.path.visible = points.length > 1;
    } else {
      this.path.geometry = new THREE.BufferGeometry();
      this.path.visible = false;
    }
    this.setTime(0);
  }

  /** Put the drone where the flight was `elapsed` seconds after its start. */
  setTime(elapsed) {
    if (!this.flight) return;
    this.pose = poseAt(this.flight, elapsed);
    if (!this.pose) return;
    this.drone.position.set(...this.pose.position);
    this.drone.quaternion.set(...this.pose.quaternion);
    this.drone.visible = true;
    this.map.dirty = true;
  }

  /** Put the drone where its flights (flightAt) put it at wall clock `wall` (Unix seconds). */
  setWall(flights, wall) {
    const at = flightAt(flights, wall);
    if (!at) return;
    if (at.flight !== this.flight) this.show(at.flight);
    this.setTime(at.elapsed);
  }

  hide() {
    this.flight = null;
    this.pose = null;
    this.drone.visible = this.path.visible = false;
    this.map.dirty = true;
  }

  /** Take the drone and its path out of the scene for good. */
  dispose() {
    this.hide();
    this.map.scene.remove(this.drone, this.path);
    this.path.geometry.dispose();
    this.drone.traverse((o) => o.geometry?.dispose());
  }
}

/** Plays recorded flights over the map at `speed` x real time, one drone or several at once on
 * one wall clock (a race's pilots); call tick(now) every frame. The clock runs from `from` to
 * `to` (Unix seconds, the flights' started_at clock) and the replay stops by itself at `to`. */
export class FlightReplay {
  constructor(mapView) {
    this.map = mapView;
    this.single = null; // play()'s drone, made on first use
    this.tracks = []; // [{marker, flights}]: a drone and the flights it replays
    this.playing = false;
    this.paused = false;
    this.elapsed = 0; // seconds of replay clock since `from`
    this.pausedAt = null; // performance.now() when paused
    this.from = 0;
    this.to = 0;
    this.speed = 1;
    this.onStop = null; // called once when the replay ends or is stopped: (ended: boolean)
  }

  /** The drone that play() flies: amber, translucent, along its path. */
  get marker() {
    this.single ??= new FlightMarker(this.map, { colour: 0xffb300, opacity: 0.8, name: "replay" });
    return this.single;
  }

  /** Replay one recorded flight (the amber drone along its path), gone 2 s after its end. */
  play(flight, speed = 1) {
    const from = flight.started_at ?? 0;
    this.playTracks([{ marker: this.marker, flights: [flight] }], { from, to: from + flight.duration_s + 2, speed });
  }

  /** Replay several drones at once: tracks [{marker, flights}], each marker flying its flights
   * (FlightMarker.setWall) on the one clock from `from` to `to` (Unix seconds). onStop(ended):
   * called once, when the clock reaches `to` (true) or the replay is stopped (false). */
  playTracks(tracks, { from, to, speed = 1, onStop = null }) {
    this.stop();
    this.tracks = tracks;
    this.from = from;
    this.to = Math.max(from, to);
    this.speed = speed;
    this.onStop = onStop;
    this.elapsed = 0;
    this.anchor = { now: performance.now(), elapsed: 0 };
    this.playing = true;
    this.paused = false;
    this.pausedAt = null;
    this.#place();
  }

  /** The replay's clock now, Unix seconds. */
  get clock() {
    return this.from + this.elapsed;
  }

  get duration() {
    return this.to - this.from;
  }

  /** Hold the clock (on: true) or let it run on from where it stands. */
  pause(on = true) {
    if (!this.playing || on === this.paused) return;
    this.paused = on;
    this.anchor = { now: performance.now(), elapsed: this.elapsed };
    this.pausedAt = on ? this.anchor.now : null; // a draw after it shows the held drones
    this.map.dirty = true; // the held picture is drawn
  }

  stop(ended = false) {
    const wasPlaying = this.playing;
    this.playing = false;
    this.paused = false;
    this.pausedAt = null;
    for (const { marker } of this.tracks) marker.hide();
    const onStop = this.onStop;
    this.onStop = null;
    if (wasPlaying) onStop?.(ended);
  }

  tick(now) {
    if (!this.playing || this.paused) return;
    // A frame's time may precede a start or resume made during that frame.
    this.elapsed = this.anchor.elapsed + Math.max(0, ((now - this.anchor.now) / 1000) * this.speed);
    if (this.elapsed > this.duration) {
      this.elapsed = this.duration;
      this.stop(true);
      return;
    }
    this.#place();
  }

  #place() {
    for (const { marker, flights } of this.tracks) marker.setWall(flights, this.clock);
  }
}

/** The ghost of a recorded flight during a new one: its clock starts when the live drone
 * leaves the ground (or spawns in the air), so both flights are compared from their starts. */
export class Ghost {
  constructor(mapView) {
    this.marker = new FlightMarker(mapView);
    this.flight = null;
    this.liveStart = null; // drone_state.timestamp when the live flight began
    this.lastMode = null;
  }

  set(flight) {
    this.flight = flight;
    this.liveStart = null;
    if (flight) this.marker.show(flight);
    else this.marker.hide();
  }

  /** Every live drone_state: starts the ghost's clock at the live flight's start. */
  droneState(state) {
    if (!this.flight) return;
    const airborne = !GROUNDED.has(state.mode);
    if (airborne && (this.liveStart === null || GROUNDED.has(this.lastMode))) this.liveStart = state.timestamp;
    this.lastMode = state.mode;
    this.marker.setTime(this.liveStart === null ? 0 : state.timestamp - this.liveStart);
  }
}
