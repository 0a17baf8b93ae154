// A viewer link's client: watches a session read-only over /ws/sessions/{id}/view (the link is
// the page's fragment, #watch=<id>&token=<viewer token>, which the browser never sends to a
// server). It dispatches the same events as SessionClient ("status", "welcome", "pose",
// "map_chunk", "drone_state", "drone_event", "error"), so the page draws a watched session as
// its own; it sends nothing (commands return null: a viewer's controls are off). It reconnects
// through the same path as the session's own socket (connection.js), until the link is refused.

import { SocketClient, State } from "./connection.js";

/** The session id and viewer token of a viewer link's fragment, or null. */
export function viewerLink(hash = window.location.hash) {
  const params = new URLSearchParams(hash.replace(/^#/, ""));
  const id = params.get("watch");
  const token = params.get("token");
  return id && token ? { id, token } : null;
}

export class ViewerClient extends SocketClient {
  constructor(protocol, { id, token }, { baseUrl = window.location.origin } = {}) {
    super(protocol, { baseUrl, waits: false }); // nothing it sends could wake it
    this.link = { id, token };
    this.viewer = true;
    this.latencyMs = NaN; // a viewer sends no frames; the HUD reads these
    this.lastLatencyMs = NaN;
    this.busy = true;
  }

  get session() {
    return { id: this.link.id, token: null };
  }

  /** Connect (and reconnect after a dropped connection, until the link is refused). */
  open() {
    this.attempt = 0;
    this.connect();
  }

  connect() {
    const { id, token } = this.link;
    this.openSocket(`/ws/sessions/${encodeURIComponent(id)}/view?token=${encodeURIComponent(token)}`, "watching: connecting");
  }

  received(message) {
    if (message.type === "welcome") this.setStatus(State.OPEN, `watching session ${this.link.id} (read-only)`);
  }

  endedMessage() {
    return "the viewer link was revoked, or the session ended";
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
