// Starting, stopping and ending the page's session: a capture source (a replayed sequence or
// live WebXR AR), the session it streams into (continued, new, or in a saved room), the
// Streamer between them, and what a reopened page restores (the map so far, where a replay
// was). Events: "busy" {busy} while a start is under way, "streaming" {running, reason} when
// the stream starts or stops, "failed" {mode, error} when a start fails, "tap-needed" when live
// AR waits for the user's tap.

import { Streamer } from "../capture/streamer.js";
import { LiveSource } from "../capture/sources/live.js";
import { ReplaySequence, ReplaySource } from "../capture/sources/replay.js";
import { parsePly } from "../formats/ply.js";
import { parseTumPositions } from "../formats/tum.js";
import { State } from "../network/connection.js";

const REPLAY_KEY = "dronesim.replay"; // where a replay was, to go on there after a reload
// The server's demo sequences (routes_client.py DEMO_PRESETS), by capture mode.
const DEMO_URLS = { demo: "/api/demo", "demo-small": "/api/demo?preset=small", "demo-loop": "/api/demo?preset=loop" };

export class SessionControl extends EventTarget {
  /**
   * @param {object} parts
   * @param {import("../network/connection.js").SessionClient} parts.client
   * @param {import("./state.js").SessionState} parts.state
   * @param {import("../network/protocol.js").Protocol} parts.protocol
   * @param {import("../ui/hud.js").Hud} parts.hud what the user is told
   * @param {import("../views/ar_view.js").ARView} parts.ar live AR draws its overlay with its renderer
   * @param {import("../views/frame_depths.js").FrameDepths} parts.frameDepths keeps sent frames' depth
   * @param {import("../network/page_load.js").PageLoad} parts.meter
   * @param {(file: File) => Promise<ReplaySequence>} parts.upload an iPhone recording -> a sequence
   * @param {(view: string) => void} parts.setView
   */
  constructor({ client, state, protocol, hud, ar, frameDepths, meter, upload, setView }) {
    super();
    Object.assign(this, { client, state, protocol, hud, ar, frameDepths, meter, upload, setView });
    this.source = null;
    this.streamer = null;
    this.hello = null;
    client.addEventListener("status", ({ detail }) => this.#statusChanged(detail.state));
    state.addEventListener("error", ({ detail: error }) => {
      if (error.seq !== undefined) this.streamer?.dropImagesUpTo(error.seq);
    });
  }

  /**
   * Start streaming from a capture mode into a session.
   * @param {{mode?: "demo"|"demo-small"|"demo-loop"|"folder"|"iphone"|"live", fps?: number, fresh?: boolean,
   *   room?: boolean, loops?: boolean, files?: FileList, recording?: File}} options
   *   loops: a new session closes loops (the server's setting otherwise); the demo there and
   *   back always starts a new session that does, as showing it is what it is for.
   */
  async start({ mode = "demo", fps = 15, fresh = false, room = false, loops = false, files = null, recording = null } = {}) {
    if (mode === "demo-loop") [fresh, loops] = [true, true];
    this.stopStreaming();
    this.source?.stop?.();
    this.#busy(true);
    try {
      const source = await this.#openSource(mode, { files, recording });
      if (!source) return;
      this.source = source;
      const info = source.info;
      const hello = this.protocol.hello({ ...info, recorded: source.kind === "replay" });
      const { id, resumed } = await this.client.open(hello, { fresh, room, loopClosure: loops || null });
      if (!resumed) this.state.reset();
      this.hud.toast(resumed ? `continuing session ${id}` : `new session ${id}`, "ok");
      this.hello = hello;
      this.state.setCamera(info);
      if (resumed && this.state.seen.mapPoints === 0) this.#restoreMap();
      this.#stream(source, { id, resumed, fps });
    } catch (exc) {
      console.error(exc);
      this.hud.showBanner(exc.message, "error", 10000);
      this.dispatchEvent(new CustomEvent("failed", { detail: { mode, error: exc } }));
      this.#changed({ running: false });
      throw exc;
    } finally {
      this.#busy(false);
    }
  }

  /** The capture source of a mode, started; null when live AR must wait for the user's tap. */
  async #openSource(mode, { files, recording }) {
    if (mode === "live") {
      if (navigator.userActivation && !navigator.userActivation.isActive) {
        // A browser starts AR only from the user's tap (e.g. ?autostart=live): ask for it.
        this.dispatchEvent(new CustomEvent("tap-needed"));
        this.hud.showBanner("Tap Start to begin live AR (a browser starts AR only from a tap).", "info", 30000);
        return null;
      }
      this.hud.hideBanner();
      const source = new LiveSource(this.ar, document.querySelector("#overlay-root"));
      source.onEnd = () => this.stopStreaming("AR ended");
      this.hud.toast("starting AR…");
      this.setView("ar"); // the camera fills the screen; the Map button overlays the map
      source.info = await source.start();
      return source;
    }
    if (mode in DEMO_URLS) this.hud.toast("loading the demo sequence (the server makes it on first use, up to a minute)…");
    let sequence;
    if (mode === "folder") sequence = await ReplaySequence.fromFiles(files);
    else if (mode === "iphone") sequence = await this.upload(recording);
    else sequence = await ReplaySequence.fromServer(DEMO_URLS[mode] ?? DEMO_URLS.demo);
    const source = new ReplaySource(sequence);
    source.prefetch(0);
    return source;
  }

  /** Stream the source into the open session. A recording waits for the server rather than
   * dropping frames; a live camera cannot. A replay reopened into its session goes on where it
   * was: the camera does not jump. */
  #stream(source, { id, resumed, fps }) {
    const streamer = new Streamer(this.client, source, { fps, holdBack: source.kind === "replay", meter: this.meter });
    this.streamer = streamer;
    const place = JSON.parse(sessionStorage.getItem(REPLAY_KEY) ?? "null");
    if (resumed && source.kind === "replay" && place?.session === id && place.name === source.sequence.name) {
      streamer.tick = place.tick;
    }
    streamer.addEventListener("sent", (e) => this.frameDepths.keep(e.detail.seq, e.detail.fields));
    streamer.addEventListener("sent", () => sessionStorage.setItem(REPLAY_KEY, JSON.stringify(
      { session: id, name: source.sequence?.name, tick: streamer.tick })));
    streamer.addEventListener("state", (e) => this.#changed(e.detail));
    streamer.addEventListener("failure", (e) => this.hud.toast(`capture failed: ${e.detail.message}`, "error", 8000));
    streamer.start();
  }

  /** A page reopened into a running session: the map and trajectory made so far, from the
   * session's downloads (map_chunk messages only bring new points). */
  async #restoreMap() {
    try {
      const [{ blob: ply }, { blob: tum }] = await Promise.all([this.client.download("map.ply"),
        this.client.download("trajectory.tum")]);
      const { points, colours } = parsePly(await ply.arrayBuffer());
      this.state.restore({ points, colours, positions: parseTumPositions(await tum.text()) });
    } catch (exc) {
      console.info("no earlier map to show", exc.message);
    }
  }

  /** The picture of a sent frame, for the AR view when its pose comes (closed by the caller). */
  takeImage(seq) {
    return this.streamer?.takeImage(seq) ?? null;
  }

  stopStreaming(reason = "") {
    this.streamer?.stop(reason);
  }

  /** Start again: the stream in hand, else a new start with these options. */
  resume(options) {
    if (this.streamer) this.streamer.start();
    else this.start(options).catch(() => {}); // shown in the banner
  }

  /** End the session (the user's End session): the server saves it, the page forgets it. */
  end() {
    this.stopStreaming();
    this.client.bye("ended by the user");
    this.client.forget();
    this.streamer = null;
    this.state.reset();
    this.hud.toast("session ended", "info");
  }

  #statusChanged(state) {
    if (state === State.TAKEN_OVER) {
      this.stopStreaming("the session moved to another tab or device");
    } else if (state === State.ENDED) {
      this.stopStreaming("the session ended");
      this.client.forget();
      this.streamer = null;
    }
  }

  #busy(busy) {
    this.dispatchEvent(new CustomEvent("busy", { detail: { busy } }));
  }

  #changed({ running, reason }) {
    this.dispatchEvent(new CustomEvent("streaming", { detail: { running, reason } }));
  }
}
