// A viewer link's client: watches a session read-only over /ws/sessions/{id}/view (the link is
// the page's fragment, #watch=<id>&token=<viewer token>, which the browser never sends to a
// server). It dispatches the same events as SessionClient ("status", "welcome", "pose",
// "map_chunk", "drone_state", "drone_event", "error"), so the page draws a watched session as
// its own; it sends nothing (commands return null: a viewer's controls are off).

import { State } from "./connection.js";
import { SERVER_TO_CLIENT } from "./protocol.js";

const BACKOFF_S = [0.5, 1, 2, 4, 8];
// A revoked link or an ended session: reconnecting cannot help.
const FINAL_CLOSES = new Set(["unauthorized", "version_mismatch", "session_failed"]);

/** The session id and viewer token of a viewer link's fragment, or null. */
export function viewerLink(hash = window.location.hash) {
  const params = new URLSearchParams(hash.replace(/^#/, ""));
  const id = params.get("watch");
  const token = params.get("token");
  return id && token ? { id, token } : null;
}

export class ViewerClient extends EventTarget {
  constructor(protocol, { id, token }, { baseUrl = window.location.origin } = {}) {
    super();
    this.protocol = protocol;
    this.link = { id, token };
    this.baseUrl = baseUrl;
    this.viewer = true;
    this.state = State.IDLE;
    this.ws = null;
    this.welcome = null;
    this.attempt = 0;
    this.inFlight = new Map(); // a viewer sends no frames; the HUD reads these
    this.latencyMs = NaN;
    this.busy = true;
    this.counts = { sent: 0, poses: 0, errors: 0, reconnects: 0, bytesSent: 0, maxInFlight: 0, withDevicePose: 0 };
    this.statusLog = [];
  }

  get session() {
    return { id: this.link.id, token: null };
  }

  get isOpen() {
    return this.state === State.OPEN && this.ws?.readyState === WebSocket.OPEN;
  }

  #status(state, message = "") {
    this.state = state;
    this.statusLog.push({ state, message, at: performance.now() });
    if (this.statusLog.length > 100) this.statusLog.shift();
    this.dispatchEvent(new CustomEvent("status", { detail: { state, message } }));
  }

  /** Connect (and reconnect after a dropped connection, until the link is refused). */
  open() {
    this.attempt = 0;
    this.#connect();
  }

  #connect() {
    const scheme = this.baseUrl.startsWith("https") ? "wss" : "ws";
    const host = this.baseUrl.replace(/^https?:\/\//, "");
    const { id, token } = this.link;
    this.#status(this.attempt ? State.RECONNECTING : State.CONNECTING, "watching: connecting");
    const ws = new WebSocket(`${scheme}://${host}/ws/sessions/${encodeURIComponent(id)}/view?token=${encodeURIComponent(token)}`);
    ws.binaryType = "arraybuffer";
    this.ws = ws;
    ws.onmessage = (event) => this.#receive(event.data);
    ws.onclose = (event) => this.#closed(ws, event);
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
      this.#status(State.OPEN, `watching session ${this.link.id} (read-only)`);
    } else if (message.type === "pose") {
      this.counts.poses += 1;
    } else if (message.type === "error") {
      this.counts.errors += 1;
    }
    this.dispatchEvent(new CustomEvent("message", { detail: message }));
    this.dispatchEvent(new CustomEvent(message.type, { detail: message }));
  }

  #closed(ws, event) {
    if (ws !== this.ws) return;
    this.ws = null;
    this.welcome = null;
    const close = this.protocol.closeCodes[event.code]?.name;
    if (this.stopping) {
      this.#status(State.IDLE, "stopped watching");
    } else if (FINAL_CLOSES.has(close)) {
      this.#status(State.ENDED, "the viewer link was revoked, or the session ended");
    } else {
      const delay = BACKOFF_S[Math.min(this.attempt, BACKOFF_S.length - 1)];
      this.attempt += 1;
      this.counts.reconnects += 1;
      this.#status(State.RECONNECTING, `connection lost; reconnecting in ${delay} s`);
      this.retryTimer = setTimeout(() => this.#connect(), delay * 1000);
    }
  }

  /** A viewer commands nothing: the server would refuse it (read_only). */
  command() {
    return null;
  }

  sendFrame() {
    return null;
  }

  skipSeq() {}

  wake() {}

  bye() {
    this.close();
  }

  close() {
    clearTimeout(this.retryTimer);
    this.stopping = true;
    this.ws?.close(1000, "viewer closed");
  }

  forget() {}

  async download() {
    throw new Error("a viewer link cannot download the session's files");
  }

  downloadMap() {
    return this.download();
  }
}
