// Recorded flights on the map view: the session's flights over REST, a flight's pose at any
// time (states interpolated), a replay of a flight, and a translucent "ghost" of a chosen (or
// the best) flight flying beside the live drone during a new flight. A flight is the JSON of
// GET /api/sessions/{id}/flights/{flight_id}.json (shared/PROTOCOL.md, "Flight recordings"):
// rows of state_columns (t s, x y z m and vx vy vz m/s in the world frame, qx qy qz qw, mode).

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

/** A translucent drone and its recorded path, drawn in a MapView's scene. */
export class FlightMarker {
  constructor(mapView, { colour = 0x4dd0e1, opacity = 0.45, name = "ghost" } = {}) {
    this.map = mapView;
    this.drone = createDrone();
    this.drone.name = name;
    this.drone.traverse((o) => {
      if (!o.material) return;
      o.material = o.material.clone();
      o.material.color?.setHex(colour);
      o.material.emissive?.setHex(0x000000);
      o.material.transparent = true;
      o.material.opacity = opacity;
      o.material.depthWrite = false;
    });
    this.drone.visible = false;
    this.path = new THREE.Line(new THREE.BufferGeometry(), new THREE.LineBasicMaterial({ color: colour, transparent: true, opacity: 0.6 }));
    this.path.frustumCulled = false;
    this.path.visible = false;
    mapView.scene.add(this.drone, this.path);
    this.flight = null;
    this.pose = null;
  }

  show(flight) {
    this.flight = flight;
    const c = Object.fromEntries(flight.state_columns.map((name, i) => [name, i]));
    const points = flight.states.map((r) => new THREE.Vector3(r[c.x], r[c.y], r[c.z]));
    this.path.geometry.dispose();
    this.path.geometry = new THREE.BufferGeometry().setFromPoints(points);
    this.path.visible = points.length > 1;
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

  hide() {
    this.flight = null;
    this.pose = null;
    this.drone.visible = this.path.visible = false;
    this.map.dirty = true;
  }
}

/** Plays a recorded flight over the map at `speed` x real time; call tick(now) every frame. */
export class FlightReplay {
  constructor(mapView) {
    this.marker = new FlightMarker(mapView, { colour: 0xffb300, opacity: 0.8, name: "replay" });
    this.playing = false;
    this.elapsed = 0;
  }

  play(flight, speed = 1) {
    this.marker.show(flight);
    this.speed = speed;
    this.startedAt = performance.now();
    this.elapsed = 0;
    this.playing = true;
  }

  stop() {
    this.playing = false;
    this.marker.hide();
  }

  tick(now) {
    if (!this.playing) return;
    this.elapsed = ((now - this.startedAt) / 1000) * this.speed;
    this.marker.setTime(this.elapsed);
    if (this.elapsed > this.marker.flight.duration_s + 2) this.stop(); // ended: gone after 2 s
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
