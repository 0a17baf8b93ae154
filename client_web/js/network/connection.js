// The page's WebSocket to a session, and its one reconnect path. SocketClient decodes what the
// server sends and, when the socket closes, does what protocol.json's close code says
// (close_codes[].reconnect: never, retry, when_active, when_asked). SessionClient is the
// phone's own session: created over REST, spoken to over its WebSocket (hello -> welcome ->
// frames and commands; poses, map chunks, drone state and events back), with flow control
// (frames in flight until a pose or error with seq >= theirs). The id, token, hello and next
// seq survive a reload in sessionStorage. A viewer link's client (viewer.js) shares the socket.
// A page opened from an invitation (#join=...) opens its session in the inviting session's
// shared room.

import { SERVER_TO_CLIENT } from "./protocol.js";
import { createSession, downloadFile, sessionStatus } from "./session_rest.js";

const STORE_KEY = "dronesim.session";
const ROOM_KEY = "dronesim.room"; // the last ended session: its id and token open its room
const BACKOFF_S = [0.5, 1, 2, 4, 8];
const LATENCY_WINDOW = 30;

export const State = Object.freeze({
  IDLE: "idle", // no socket, nothing to do
  CONNECTING: "connecting",
  OPEN: "open", // welcome received
  RECONNECTING: "reconnecting",
  PAUSED: "paused", // the server closed an idle socket: reopens on the next frame or command
  ENDED: "ended", // refused for good (a close whose reconnect is "never")
  TAKEN_OVER: "taken_over", // another socket with the token has the session; stays saved here
});

/** A socket to one session. Events: "status" {state, message}, "message" (every decoded server
 * message), and one event per message type ("welcome", "pose", "map_chunk", ...). Subclasses
 * say where to connect (connect()), what to send on open (opened()) and what a message means to
 * them (received()); `waits`: whether the page may wait for activity or the user before
 * reconnecting (a viewer, which sends nothing, always retries). */
export class SocketClient extends EventTarget {
  constructor(protocol, { baseUrl = window.location.origin, waits = true } = {}) {
    super();
    this.protocol = protocol;
    this.baseUrl = baseUrl;
    this.waits = waits;
    this.state = State.IDLE;
    this.ws = null;
    this.welcome = null;
    this.inFlight = new Map(); // seq -> performance.now() when sent
    this.attempt = 0;
    this.stopping = false;
    // withDevicePose: frames sent with the device's own pose (T_device_camera).
    this.counts = { sent: 0, poses: 0, errors: 0, reconnects: 0, bytesSent: 0, maxInFlight: 0, withDevicePose: 0 };
    this.statusLog = []; // [{state, message, at}] for the HUD's history and the tests
  }

  get isOpen() {
    return this.state === State.OPEN && this.ws?.readyState === WebSocket.OPEN;
  }

  setStatus(state, message = "") {
    this.state = state;
    this.statusLog.push({ state, message, at: performance.now() });
    if (this.statusLog.length > 100) this.statusLog.shift();
    this.dispatchEvent(new CustomEvent("status", { detail: { state, message } }));
  }

  /** Open the socket at `path` (below ws[s]://host), saying `message` meanwhile. */
  openSocket(path, message) {
    const scheme = this.baseUrl.startsWith("https") ? "wss" : "ws";
    const host = this.baseUrl.replace(/^https?:\/\//, "");
    this.setStatus(this.attempt ? State.RECONNECTING : State.CONNECTING, message);
    const ws = new WebSocket(`${scheme}://${host}${path}`);
    ws.binaryType = "arraybuffer";
    this.ws = ws;
    ws.onopen = () => this.opened();
    ws.onmessage = (event) => this.#receive(event.data);
    ws.onclose = (event) => this.#closed(ws, event);
  }

  connect() {
    throw new Error("a SocketClient subclass says where to connect");
  }

  opened() {}

  received() {}

  /** What ENDED says, after a close that is final. */
  endedMessage(reason) {
    return `the server ended the session: ${reason}`;
  }

  #receive(data) {
    let message;
    try {
      message = this.protocol.decode(data, SERVER_TO_CLIENT);
    } catch (exc) {
      console.warn("ignored a message that breaks the protocol", exc);
      return;
    }
    if (message.type === "welcome") {
      this.welcome = message;
      this.attempt = 0;
    } else if (message.type === "pose") {
      this.counts.poses += 1;
    } else if (message.type === "error") {
      this.counts.errors += 1;
    }
    this.received(message);
    this.dispatchEvent(new CustomEvent("message", { detail: message }));
    this.dispatchEvent(new CustomEvent(message.type, { detail: message }));
  }

  /** The one reconnect path: what the close code's `reconnect` says (protocol.json). */
  #closed(ws, event) {
    if (ws !== this.ws) return;
    this.ws = null;
    this.welcome = null;
    this.inFlight.clear(); // their answers are lost with the socket
    const reason = this.protocol.closeReason(event.code) + (event.reason ? ` (${event.reason})` : "");
    const then = this.protocol.reconnectAfter(event.code);
    if (this.stopping) {
      this.stopping = false;
      this.setStatus(State.IDLE, "disconnected");
    } else if (then === "never") {
      this.setStatus(State.ENDED, this.endedMessage(reason));
    } else if (then === "when_asked" && this.waits) {
      this.setStatus(State.TAKEN_OVER, "another tab or device took this session over");
    } else if (then === "when_active" && this.waits) {
      this.setStatus(State.PAUSED, "idle: reconnects when you stream or fly");
    } else {
      const delay = BACKOFF_S[Math.min(this.attempt, BACKOFF_S.length - 1)];
      this.attempt += 1;
      this.counts.reconnects += 1;
      this.setStatus(State.RECONNECTING, `connection lost (${reason}); reconnecting in ${delay} s`);
      this.retryTimer = setTimeout(() => this.connect(), delay * 1000);
    }
  }

  /** Reconnect a socket that waits (PAUSED; with `takeBack`, TAKEN_OVER too). Only the user's own
   * act (Start, a command) may take a session back: a frame that was being captured when the
   * session moved must not. */
  wake({ takeBack = false } = {}) {
    const asleep = this.state === State.PAUSED || (takeBack && this.state === State.TAKEN_OVER);
    if (asleep) {
      this.attempt = 0;
      this.connect();
    }
  }
}

export class SessionClient extends SocketClient {
  /** join: an invitation ({id, token}: session_rest.js joinLink) the next new session joins */
  constructor(protocol, { storage = window.sessionStorage, roomStorage = window.localStorage,
    baseUrl = window.location.origin, join = null } = {}) {
    super(protocol, { baseUrl });
    this.invitation = join;
    this.storage = storage;
    this.roomStorage = roomStorage; // outlives the tab: a room is for coming back another day
    this.latencies = [];
    this.lastLatencyMs = NaN; // the round trip of the frame the last answer was for
    this.pending = []; // commands waiting for the connection
    this.nextCommandId = 1;
    this.saved = this.#load();
  }

  get session() {
    return this.saved ? { id: this.saved.id, token: this.saved.token } : null;
  }

  /** The id of the session whose shared room this session joined, or null (its own room). */
  get joined() {
    return this.saved?.join ?? null;
  }

  get maxInFlight() {
    return this.welcome?.max_in_flight ?? this.protocol.limits.max_in_flight;
  }

  get busy() {
    return this.inFlight.size >= this.maxInFlight;
  }

  /** Median send-to-pose latency over the last frames, milliseconds (NaN before any). */
  get latencyMs() {
    if (!this.latencies.length) return NaN;
    const sorted = [...this.latencies].sort((a, b) => a - b);
    return sorted[Math.floor(sorted.length / 2)];
  }

  #load() {
    try {
      return JSON.parse(this.storage.getItem(STORE_KEY) ?? "null");
    } catch {
      return null;
    }
  }

  #save() {
    if (this.saved) this.storage.setItem(STORE_KEY, JSON.stringify(this.saved));
    else this.storage.removeItem(STORE_KEY);
  }

  /**
   * Open a session for this hello: the saved one when it is still live on the server and was
   * started with the same camera (the server keeps its map and trajectory), else a new one.
   * With `room`, a new session in the room the saved (closed) session left: it relocalises in
   * that room's map and tracks in its frame (docs/OFFLINE.md, "Rooms"). A page opened from an
   * invitation joins the inviting session's shared room (a new session, unless the saved one
   * joined it already). `loopClosure` true or false asks a new session to close loops or not
   * (null: the server's setting).
   * @returns {Promise<{id: string, token: string, resumed: boolean}>}
   */
  async open(hello, { fresh = false, room = false, loopClosure = null } = {}) {
    this.close();
    let resumed = false;
    const join = room ? null : this.invitation;
    // A session saved before the invitation was opened is not in its room: a new one is.
    const same = this.saved && JSON.stringify(this.saved.camera) === JSON.stringify(cameraOf(hello)) &&
      (this.saved.join ?? null) === (join?.id ?? null);
    if (room) {
      // The room of the last session ended here, else of the session still remembered.
      const last = JSON.parse(this.roomStorage.getItem(ROOM_KEY) ?? "null") ?? this.saved;
      if (!last) throw new Error("no earlier session on this device to continue the room of");
      const created = await createSession(this.baseUrl, { token: last.token, room: last.id, loopClosure });
      this.saved = { id: created.id, token: created.token, nextSeq: 0, camera: cameraOf(hello) };
    } else if (!fresh && same) {
      try {
        resumed = !(await sessionStatus(this.baseUrl, this.saved)).closed;
      } catch {
        resumed = false;
      }
    }
    if (!resumed && join) {
      const created = await createSession(this.baseUrl, { join: join.id, token: join.token }).catch((exc) => {
        throw Object.assign(new Error(`Could not join the shared room: ${exc.message}`), { status: exc.status });
      });
      this.saved = { id: created.id, token: created.token, nextSeq: 0, camera: cameraOf(hello), join: join.id };
    } else if (!resumed && !room) {
      const created = await createSession(this.baseUrl, { loopClosure });
      this.saved = { id: created.id, token: created.token, nextSeq: 0, camera: cameraOf(hello) };
    }
    this.saved.hello = hello;
    this.#save();
    this.attempt = 0;
    this.connect();
    return { ...this.session, resumed };
  }

  connect() {
    if (!this.saved) return;
    const { id, token } = this.saved;
    this.openSocket(`/ws/sessions/${encodeURIComponent(id)}?token=${encodeURIComponent(token)}`,
      this.attempt ? `reconnecting (attempt ${this.attempt})` : "connecting");
  }

  opened() {
    this.#send(this.saved.hello);
  }

  received(message) {
    if (message.type === "welcome") {
      this.setStatus(State.OPEN, `session ${this.saved.id}`);
      for (const pendingMessage of this.pending.splice(0)) this.#send(pendingMessage);
    } else if (message.type === "pose") {
      this.#acknowledge(message.seq, true);
    } else if (message.type === "error" && message.seq !== undefined) {
      this.#acknowledge(message.seq, false);
    }
  }

  #send(message) {
    const data = this.protocol.encode(message, this.welcome?.max_message_bytes);
    this.ws.send(data);
    this.counts.bytesSent += data.byteLength;
  }

  /** One answer acknowledges every frame with seq <= its own. */
  #acknowledge(seq, measured) {
    const sentAt = this.inFlight.get(seq);
    this.lastLatencyMs = NaN;
    if (measured && sentAt !== undefined) {
      this.lastLatencyMs = performance.now() - sentAt; // this answer's own round trip
      this.latencies.push(this.lastLatencyMs);
      if (this.latencies.length > LATENCY_WINDOW) this.latencies.shift();
    }
    for (const s of this.inFlight.keys()) if (s <= seq) this.inFlight.delete(s);
  }

  /**
   * Send a frame if the socket is open and fewer than max_in_flight frames await answers.
   * @param {object} fields timestamp, colour, depth, depthFormat, depthScale, deviceCamera (see Protocol.frame)
   * @returns {number|null} the frame's seq, or null when it was not sent
   */
  sendFrame(fields) {
    this.wake();
    if (!this.isOpen || this.busy) return null;
    const seq = this.saved.nextSeq;
    const message = this.protocol.frame({ seq, ...fields });
    this.saved.nextSeq = seq + 1;
    this.#save();
    this.inFlight.set(seq, performance.now());
    this.counts.maxInFlight = Math.max(this.counts.maxInFlight, this.inFlight.size);
    this.#send(message);
    this.counts.sent += 1;
    if (message.T_device_camera) this.counts.withDevicePose += 1;
    return seq;
  }

  /** Take the next seq without sending (a camera frame skipped while busy leaves a gap). */
  skipSeq() {
    if (this.saved) this.saved.nextSeq += 1;
  }

  /**
   * Send a drone command; queued until the welcome when the socket is (re)connecting. Sticks
   * are never queued: stale sticks are worse than none.
   * @returns {number|null} the command's id
   */
  command(name, fields = {}) {
    if (!this.saved) return null;
    const id = this.nextCommandId++;
    const message = this.protocol.command(id, name, fields);
    this.wake({ takeBack: true });
    if (this.isOpen) this.#send(message);
    else if (name !== "sticks") this.pending.splice(0, this.pending.length, message);
    else return null;
    return id;
  }

  /** Say goodbye and close: the server answers frames in flight, then closes with 1000. */
  bye(reason = "user stopped") {
    clearTimeout(this.retryTimer);
    if (this.isOpen) {
      this.stopping = true;
      this.#send(this.protocol.bye(reason));
    } else {
      this.close();
    }
  }

  /** Drop the socket without a goodbye (the session stays open on the server). */
  close() {
    clearTimeout(this.retryTimer);
    const ws = this.ws;
    this.ws = null;
    this.welcome = null;
    this.inFlight.clear();
    this.pending = [];
    this.stopping = false;
    if (ws) {
      ws.onclose = ws.onmessage = ws.onopen = null;
      ws.close(1000, "client closed");
    }
    if (this.state !== State.IDLE) this.setStatus(State.IDLE, "disconnected");
  }

  /** Forget the saved session (the next open creates a new one). */
  forget() {
    this.close();
    // The ended session may leave a room: remembered for "Continue in a saved room".
    if (this.saved) this.roomStorage.setItem(ROOM_KEY, JSON.stringify({ id: this.saved.id, token: this.saved.token }));
    this.saved = null;
    this.#save();
  }

  /** A session download (map.ply, mesh.ply, trajectory.tum) as a Blob, with the token as
   * Authorization header; `signal` may abort it. */
  download(name, signal = undefined) {
    return downloadFile(this.baseUrl, this.saved ?? {}, name, signal);
  }

  /** The fused map as a PLY file. */
  downloadMap() {
    return this.download("map.ply");
  }
}

/** What the server's session remembers of the camera: a reconnect must present the same. */
function cameraOf(hello) {
  return { intrinsics: hello.intrinsics, colour_size: hello.colour_size };
}
