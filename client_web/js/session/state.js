// What the page knows of its session, as one event target the views subscribe to (each view's
// follow(state)): the server's messages, decoded and counted, plus what the page itself learns
// (a map restored from the session's downloads, a new session). `seen` counts what came, for
// the HUD's history, the debugging snapshot and the browser tests.
//
// Events (detail):
//   "status"      {state, message}: the connection's (network/connection.js State)
//   "camera"      {intrinsics: [fx, fy, cx, cy] px, colourSize: [w, h] px, gravity: [x, y, z] in
//                 the first camera's frame or null}: the camera a new stream sends from
//   "pose"        a pose message (T_world_camera row-major, metres; seq, state, recovery...)
//   "map"         {points: Float32Array xyz, colours: Uint8Array rgb, reset, total}: map points
//                 added (reset: they replace the map), total points in the map after them
//   "trail"       {positions: [[x, y, z]...]}: camera positions to extend the trajectory with
//   "corrected"   a map_corrected message: the server closed a loop
//   "drone"       a drone_state message
//   "drone_event" a drone_event message
//   "course"      a course message
//   "room"        the shared room's pilots (session/room.js roomPilots), or null: no room
//                 message for a while (the room has fewer than two live phones), or a reset
//   "error"       an error message (cancelable: a listener that handles it calls preventDefault)
//   "reset"       no detail: a new session, or the session ended; the views clear

import { mapChunkArrays } from "../network/protocol.js";
import { STALE_MS, roomPilots } from "./room.js";

const KEPT = { events: 200, errors: 200, modeLog: 100, corrections: 50 };

function emptySeen() {
  return { poses: 0, states: {}, recovery: {}, lastPose: null, droneStates: 0, lastDrone: null, modeLog: [], events: [], errors: [],
    chunks: 0, chunkPoints: 0, mapPoints: 0, serverDropped: 0, serverFailures: {}, shownSeq: null, corrections: [], mapResets: 0,
    rooms: 0, lastRoom: null };
}

function keep(list, item, most) {
  list.push(item);
  if (list.length > most) list.shift();
}

export class SessionState extends EventTarget {
  /**
   * @param {import("../network/connection.js").SocketClient} client the session's socket
   * @param {{meter?: import("../network/page_load.js").PageLoad}} options meter: times each pose's
   *   handling, by every view, as the page's "receive" work
   */
  constructor(client, { meter = null } = {}) {
    super();
    this.client = client;
    this.meter = meter;
    this.seen = emptySeen();
    this.room = null; // the shared room's pilots (room.js), while its messages come
    const on = (type, fn) => client.addEventListener(type, ({ detail }) => fn(detail));
    on("status", (status) => this.#emit("status", status));
    on("pose", (pose) => (meter ? meter.time("receive", () => this.#pose(pose)) : this.#pose(pose)));
    on("map_chunk", (chunk) => this.#mapChunk(chunk));
    on("map_corrected", (correction) => this.#corrected(correction));
    on("drone_state", (drone) => this.#drone(drone));
    on("drone_event", (event) => {
      keep(this.seen.events, event, KEPT.events);
      this.#emit("drone_event", event);
    });
    on("course", (course) => this.#emit("course", course));
    on("room", (room) => this.#room(room));
    on("error", (error) => {
      keep(this.seen.errors, error, KEPT.errors);
      this.dispatchEvent(new CustomEvent("error", { detail: error, cancelable: true }));
    });
  }

  /** The round trip of the frame the last pose was for, milliseconds (NaN when unmeasured). */
  get lastLatencyMs() {
    return this.client.lastLatencyMs ?? NaN;
  }

  /** A new session, or none: the counters start again and the views clear. */
  reset() {
    this.seen = emptySeen();
    this.#roomGone();
    this.#emit("reset", null);
  }

  /** The camera of the stream that starts now (its source's info). */
  setCamera({ intrinsics, colourSize, gravity = null }) {
    this.#emit("camera", { intrinsics, colourSize, gravity });
  }

  /** The map and trajectory a reopened page downloaded (map_chunk messages only bring new points). */
  restore({ points, colours, positions }) {
    this.#addPoints(points, colours, false, points.length > 0 ? true : null); // map.ply came: a surface
    this.#emit("trail", { positions });
  }

  #emit(type, detail) {
    this.dispatchEvent(new CustomEvent(type, { detail }));
  }

  #pose(pose) {
    const s = this.seen;
    s.poses += 1;
    s.states[pose.state] = (s.states[pose.state] ?? 0) + 1;
    if (pose.recovery) s.recovery[pose.recovery] = (s.recovery[pose.recovery] ?? 0) + 1;
    s.lastPose = { seq: pose.seq, timestamp: pose.timestamp, state: pose.state, inliers: pose.inliers,
      T_world_camera: pose.T_world_camera, recovery: pose.recovery ?? null };
    s.serverDropped = pose.dropped;
    s.serverFailures = pose.failures ?? {};
    this.#emit("pose", pose);
    s.shownSeq = pose.seq;
  }

  #mapChunk(chunk) {
    const { points, colours } = mapChunkArrays(chunk);
    const reset = chunk.reset === true;
    this.seen.chunks += 1;
    if (reset) this.seen.mapResets += 1;
    this.seen.chunkPoints += chunk.count;
    this.#addPoints(points, colours, reset, typeof chunk.surface === "boolean" ? chunk.surface : null);
  }

  /** surface: whether the server's map has a surface to download (map_chunk.surface), null
   * when not said. */
  #addPoints(points, colours, reset, surface = null) {
    const total = (reset ? 0 : this.seen.mapPoints) + points.length / 3;
    this.seen.mapPoints = total;
    this.#emit("map", { points, colours, reset, total, surface });
  }

  /** The server closed a loop: its keyframes moved, and the map is re-fused (the chunks that
   * follow start with reset). Poses from correction.from_seq on are in the corrected world. */
  #corrected(correction) {
    keep(this.seen.corrections, { loops: correction.loops, from_seq: correction.from_seq,
      keyframes: correction.keyframes.length }, KEPT.corrections);
    this.#emit("corrected", correction);
  }

  /** A room message: the room's pilots; forgotten when the next does not come in time. */
  #room(message) {
    this.seen.rooms += 1;
    this.seen.lastRoom = message;
    this.room = roomPilots(message);
    clearTimeout(this.roomTimer);
    this.roomTimer = setTimeout(() => this.#roomGone(), STALE_MS);
    this.#emit("room", this.room);
  }

  #roomGone() {
    clearTimeout(this.roomTimer);
    if (!this.room) return;
    this.room = null;
    this.#emit("room", null);
  }

  #drone(drone) {
    const s = this.seen;
    s.droneStates += 1;
    if (s.lastDrone?.mode !== drone.mode) keep(s.modeLog, { mode: drone.mode, command_id: drone.command_id ?? null }, KEPT.modeLog);
    s.lastDrone = drone;
    this.#emit("drone", drone);
  }
}
