// One server session: created over REST, spoken to over its WebSocket (hello -> welcome ->
// frames and commands; poses, map chunks, drone state and events back), with flow control
// (frames in flight until a pose or error with seq >= theirs) and automatic reconnection into
// the same session. The id, token, hello and next seq survive a reload in sessionStorage.

import { SERVER_TO_CLIENT } from "./protocol.js";

const STORE_KEY = "dronesim.session";
const ROOM_KEY = "dronesim.room"; // the last ended session: its id and token open its room
const BACKOFF_S = [0.5, 1, 2, 4, 8];
// Closes (protocol.json names) after which reconnecting cannot help: the hello or the session
// itself is refused.
const FINAL_CLOSES = new Set(["version_mismatch", "bad_hello", "unauthorized", "session_failed"]);
const LATENCY_WINDOW = 30;

export const State = Object.freeze({
  IDLE: "idle", // no socket, nothing to do
  CONNECTING: "connecting",
  OPEN: "open", // welcome received
  RECONNECTING: "reconnecting",
  PAUSED: "paused", // the server closed an idle socket: reopens on the next frame or command
  ENDED: "ended", // refused for good (bad hello, unknown or closed session)
  TAKEN_OVER: "taken_over", // another socket with the token has the session; stays saved here
});

/** Events: "status" {state, message}, "message" (every decoded server message), and one event
 * per message type ("pose", "map_chunk", "drone_state", "drone_event", "error", "welcome"). */
export class SessionClient extends EventTarget {
  constructor(protocol, { storage = window.sessionStorage, roomStorage = window.localStorage,
    baseUrl = window.location.origin } = {}) {
    super();
    this.protocol = protocol;
    this.storage = storage;
    this.roomStorage = roomStorage; // outlives the tab: a room is for coming back another day
    this.baseUrl = baseUrl;
    this.state = State.IDLE;
    this.ws = null;
    this.welcome = null;
    this.inFlight = new Map(); // seq -> performance.now() when sent
    this.latencies = [];
    this.lastLatencyMs = NaN; // the round trip of the frame the last answer was for
    this.pending = []; // commands waiting for the connection
    this.attempt = 0;
    this.nextCommandId = 1;
    // withDevicePose: frames sent with the device's own pose (T_device_camera).
    this.counts = { sent: 0, poses: 0, errors: 0, reconnects: 0, bytesSent: 0, maxInFlight: 0, withDevicePose: 0 };
    this.statusLog = []; // [{state, message, at}] for the HUD's history and the tests
    this.saved = this.#load();
  }

  get session() {
    return this.saved ? { id: this.saved.id, token: this.saved.token } : null;
  }

  get maxInFlight() {
    return this.welcome?.max_in_flight ?? this.protocol.limits.max_in_flight;
  }

  get busy() {
    return this.inFlight.size >= this.maxInFlight;
  }

  get isOpen() {
    return this.state === State.OPEN && this.ws?.readyState === WebSocket.OPEN;
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

  #status(state, message = "") {
    this.state = state;
    this.statusLog.push({ state, message, at: performance.now() });
    if (this.statusLog.length > 100) this.statusLog.shift();
    this.dispatchEvent(new CustomEvent("status", { detail: { state, message } }));
  }

  async #request(method, path, token, json = undefined) {
    const headers = token ? { Authorization: `Bearer ${token}` } : {};
    if (json !== undefined) headers["Content-Type"] = "application/json";
    const body = json === undefined ? undefined : JSON.stringify(json);
    const response = await fetch(`${this.baseUrl}${path}`, { method, headers, body });
    let answer = null;
    try {
      answer = await response.json();
    } catch {
      /* no body */
    }
    if (!response.ok) {
      const why = answer?.error?.message ?? answer?.detail ?? response.statusText;
      const error = new Error(`${method} ${path}: HTTP ${response.status} ${why}`);
      error.status = response.status;
      throw error;
    }
    return answer;
  }

  /**
   * Open a session for this hello: the saved one when it is still live on the server and was
   * started with the same camera (the server keeps its map and trajectory), else a new one.
   * With `room`, a new session in the room the saved (closed) session left: it relocalises in
   * that room's map and tracks in its frame (docs/OFFLINE.md, "Rooms"). `loopClosure` true or false
   * asks a new session to close loops or not (null: the server's setting).
   * @returns {Promise<{id: string, token: string, resumed: boolean}>}
   */
  async open(hello, { fresh = false, room = false, loopClosure = null } = {}) {
    this.close();
    let resumed = false;
    const same = this.saved && JSON.stringify(this.saved.camera) === JSON.stringify(cameraOf(hello));
    if (room) {
      // The room of the last session ended here, else of the session still remembered.
      const last = JSON.parse(this.roomStorage.getItem(ROOM_KEY) ?? "null") ?? this.saved;
      if (!last) throw new Error("no earlier session on this device to continue the room of");
      const created = await this.#request("POST", "/api/sessions", last.token, { room: last.id, loop_closure: loopClosure });
      this.saved = { id: created.id, token: created.token, nextSeq: 0, camera: cameraOf(hello) };
    } else if (!fresh && same) {
      try {
        const status = await this.#request("GET", `/api/sessions/${this.saved.id}`, this.saved.token);
        resumed = !status.closed;
      } catch {
        resumed = false;
      }
    }
    if (!resumed && !room) {
      const created = await this.#request("POST", "/api/sessions", null, { loop_closure: loopClosure });
      this.saved = { id: created.id, token: created.token, nextSeq: 0, camera: cameraOf(hello) };
    }
    this.saved.hello = hello;
    this.#save();
    this.attempt = 0;
    this.#connect();
    return { ...this.session, resumed };
  }

  #connect() {
    const { id, token } = this.saved;
    const scheme = this.baseUrl.startsWith("https") ? "wss" : "ws";
    const host = this.baseUrl.replace(/^https?:\/\//, "");
    this.#status(this.attempt ? State.RECONNECTING : State.CONNECTING,
      this.attempt ? `reconnecting (attempt ${this.attempt})` : "connecting");
    const ws = new WebSocket(`${scheme}://${host}/ws/sessions/${encodeURIComponent(id)}?token=${encodeURIComponent(token)}`);
    ws.binaryType = "arraybuffer";
    this.ws = ws;
    ws.onopen = () => this.#send(this.saved.hello);
    ws.onmessage = (event) => this.#receive(event.data);
    ws.onclose = (event) => this.#closed(ws, event);
  }

  #send(message) {
    const data = this.protocol.encode(message, this.welcome?.max_message_bytes);
    this.ws.send(data);
    this.counts.bytesSent += data.byteLength;
  }

  #receive(data) {
    let message;
    try {
      message = this.protocol.decode(data, SERVER_TO_CLIENT);
    } catch (exc) {
      console.warn("ignored a message that breaks the protocol", exc);
      return;
    }
    switch (message.type) {
      case "welcome":
        this.welcome = message;
        this.attempt = 0;
        this.#status(State.OPEN, `session ${this.saved.id}`);
        for (const pendingMessage of this.pending.splice(0)) this.#send(pendingMessage);
        break;
      case "pose":
        this.counts.poses += 1;
        this.#acknowledge(message.seq, true);
        break;
      case "error":
        this.counts.errors += 1;
        if (message.seq !== undefined) this.#acknowledge(message.seq, false);
        break;
      default:
    }
    this.dispatchEvent(new CustomEvent("message", { detail: message }));
    this.dispatchEvent(new CustomEvent(message.type, { detail: message }));
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

  #closed(ws, event) {
    if (ws !== this.ws) return;
    this.ws = null;
    this.welcome = null;
    this.inFlight.clear(); // their answers are lost with the socket
    const reason = this.protocol.closeReason(event.code) + (event.reason ? ` (${event.reason})` : "");
    const close = this.protocol.closeCodes[event.code]?.name;
    if (this.stopping) {
      this.stopping = false;
      this.#status(State.IDLE, "disconnected");
    } else if (close === "session_taken_over") {
      // Reconnecting by itself would take the session back, and two tabs would take it from
      // each other forever: only the user's Start or a command takes it back (wake).
      this.#status(State.TAKEN_OVER, "another tab or device took this session over");
    } else if (FINAL_CLOSES.has(close)) {
      this.#status(State.ENDED, `the server ended the session: ${reason}`);
    } else if (close === "idle_timeout") {
      this.#status(State.PAUSED, "idle: reconnects when you stream or fly");
    } else {
      const delay = BACKOFF_S[Math.min(this.attempt, BACKOFF_S.length - 1)];
      this.attempt += 1;
      this.counts.reconnects += 1;
      this.#status(State.RECONNECTING, `connection lost (${reason}); reconnecting in ${delay} s`);
      this.retryTimer = setTimeout(() => this.saved && this.#connect(), delay * 1000);
    }
  }

  /** Reconnect a session that the server paused for idleness; with `takeBack`, also one that
   * another tab took over. Only the user's own act (Start, a command) may take it back: a frame
   * that was being captured when the session moved must not. */
  wake({ takeBack = false } = {}) {
    const asleep = this.state === State.PAUSED || (takeBack && this.state === State.TAKEN_OVER);
    if (asleep && this.saved) {
      this.attempt = 0;
      this.#connect();
    }
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
    if (this.state !== State.IDLE) this.#status(State.IDLE, "disconnected");
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
   * Authorization header. */
  async download(name) {
    const { id, token } = this.saved ?? {};
    if (!id) throw new Error("no session yet: start streaming first");
    const response = await fetch(`${this.baseUrl}/api/sessions/${id}/${name}`, {
      headers: { Authorization: `Bearer ${token}` },
    });
    if (!response.ok) {
      let why = response.statusText;
      try {
        why = (await response.json())?.error?.message ?? why;
      } catch {
        /* not json */
      }
      throw new Error(`${name} download failed: HTTP ${response.status} ${why}`);
    }
    return { blob: await response.blob(), filename: `${id}-${name}` };
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
