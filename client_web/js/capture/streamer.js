// The capture loop: a camera that "captures" at up to `fps`; a frame captured while the session
// already has max_in_flight frames unanswered or being packed (or is still reading the previous
// one, or is not connected) is skipped, as a phone's camera would drop it. A source may hand its
// frame over once its pixels are read and pack it (JPEG, zlib) while the next frame is read:
// reading and packing overlap, and frames are still sent in the order they were captured. A
// recording (holdBack) has no reason to drop frames: it says so in its hello (recorded), sends a
// frame while the server has room to queue it (the welcome's queued_frames), or at its own rate,
// whichever is slower; while the server is behind, its clock
// stops and the frame waits, so a slow server gives a slower replay, never a lost one. Sent
// frames keep their image for the AR view until their pose arrives.

const HOLD_POLL_MS = 10; // how often a held-back recording looks for room again

export class Streamer extends EventTarget {
  /**
   * @param {import("../network/connection.js").SessionClient} client
   * @param {{capture: (tick: number, timestamp: number) => Promise<object|null>, keep?: Function}} source
   * @param {{fps?: number, holdBack?: boolean, meter?: import("../network/page_load.js").PageLoad}} options
   *   meter: counts the main thread's time to send each frame as "send"
   */
  constructor(client, source, { fps = 15, holdBack = false, meter = null } = {}) {
    super();
    this.client = client;
    this.source = source;
    this.fps = fps;
    this.running = false;
    this.tick = 0;
    this.capturing = false;
    this.packing = 0; // frames read, not yet sent (with those in flight, <= max_in_flight)
    this.sendChain = Promise.resolve(); // packed frames go out in capture order
    this.overlapped = 0; // frames read while the one before was still being packed
    this.skipped = 0; // camera frames dropped on this side
    this.unavailable = {}; // frames the source could not give (reason -> count), e.g. "no depth"
    this.holdBack = holdBack; // a recording: wait for the server instead of dropping frames
    this.heldBack = false; // waiting for the server now
    this.heldBackMs = 0; // in all, since start
    this.images = new Map(); // seq -> ImageBitmap, until shown or answered
    this.meter = meter;
  }

  start() {
    if (this.running) return;
    this.client.wake({ takeBack: true }); // the user's Start takes back a session another tab took
    this.running = true;
    this.t0 = performance.now();
    this.firstTick = this.tick;
    this.#schedule();
    this.dispatchEvent(new CustomEvent("state", { detail: { running: true } }));
  }

  stop(reason = "") {
    if (!this.running) return;
    this.running = false;
    clearTimeout(this.timer);
    this.dispatchEvent(new CustomEvent("state", { detail: { running: false, reason } }));
  }

  #schedule() {
    const due = this.t0 + ((this.tick - this.firstTick + 1) * 1000) / this.fps;
    this.timer = setTimeout(() => this.#onTick(), Math.max(0, due - performance.now()));
  }

  async #onTick() {
    if (!this.running) return;
    // A recording sends its next frame while the server has room to queue it: as many frames in
    // flight as the welcome's queued_frames (a server that keeps only the newest frame says 1,
    // or nothing: then the next frame waits for the previous pose).
    if (this.holdBack && (this.capturing || !this.client.isOpen || this.#queueFull())) {
      if (!this.client.isOpen) this.client.wake(); // a session paused by the idle timeout reconnects
      if (!this.heldBack) {
        this.heldBack = true;
        this.heldSince = performance.now();
        this.dispatchEvent(new CustomEvent("held", { detail: { held: true } }));
      }
      this.timer = setTimeout(() => this.#onTick(), HOLD_POLL_MS);
      return;
    }
    if (this.heldBack) {
      // The recording's clock resumes from now: this frame goes at once, the next one a frame
      // period later (no burst to catch up, which would outrun the server again).
      const now = performance.now();
      this.heldBack = false;
      this.heldBackMs += now - this.heldSince;
      this.t0 = now - ((this.tick - this.firstTick + 1) * 1000) / this.fps;
      this.dispatchEvent(new CustomEvent("held", { detail: { held: false } }));
    }
    const tick = this.tick++;
    this.#schedule();
    // Frames being packed will be in flight soon: they count against max_in_flight already, so
    // a frame is not read only to find no room for it.
    const pending = this.client.inFlight.size + this.packing;
    if (this.capturing || !this.client.isOpen || pending >= this.client.maxInFlight) {
      this.skipped += 1;
      if (this.client.isOpen) this.client.skipSeq();
      else this.client.wake(); // a session paused by the server's idle timeout reconnects
      return;
    }
    this.capturing = true;
    try {
      const captured = await this.source.capture(tick, performance.now() / 1000);
      if (!this.running) {
        captured?.bitmap?.close(); // stopped while capturing (e.g. the session moved away)
        return;
      }
      if (!captured) {
        this.stop("end of the sequence");
        return;
      }
      if (captured.skip) {
        // The source had no complete frame this time (e.g. AR without depth yet): count it, go on.
        this.unavailable[captured.skip] = (this.unavailable[captured.skip] ?? 0) + 1;
        this.skipped += 1;
        this.dispatchEvent(new CustomEvent("unavailable", { detail: { reason: captured.skip } }));
        return;
      }
      if (!captured.packing) {
        this.#send(captured);
        return;
      }
      // Read, not yet packed: the next tick may read the next frame meanwhile.
      if (this.packing > 0) this.overlapped += 1;
      this.packing += 1;
      // Counted until handed to the client (not only until packed: a frame packed before the one
      // ahead of it waits in the chain, and is as good as in flight).
      this.sendChain = this.sendChain
        .then(() => captured.packing)
        .then(
          (frame) => (this.running ? this.#send({ ...frame, anchor: captured.anchor }) : frame.bitmap?.close()),
          (exc) => this.running && this.#failed(exc))
        .finally(() => (this.packing -= 1));
    } catch (exc) {
      this.#failed(exc);
    } finally {
      this.capturing = false;
    }
  }

  /** A recording's frames already fill what the server queues for it (see #onTick). */
  #queueFull() {
    const queued = Math.min(this.client.welcome?.queued_frames ?? 1, this.client.maxInFlight);
    return this.client.inFlight.size + this.packing >= queued;
  }

  /** Send a captured frame ({fields, bitmap, anchor?, index?}), or count it skipped when the
   * session has no room for it now. */
  #send(captured) {
    if (this.meter) this.meter.time("send", () => this.#sendNow(captured));
    else this.#sendNow(captured);
  }

  #sendNow(captured) {
    const seq = this.client.sendFrame(captured.fields);
    if (seq === null) {
      this.skipped += 1;
      captured.bitmap?.close();
      return;
    }
    this.images.set(seq, captured.bitmap);
    if (captured.anchor) this.source.keep?.(seq, captured.anchor);
    this.dispatchEvent(new CustomEvent("sent", { detail: { seq, index: captured.index, fields: captured.fields } }));
  }

  #failed(exc) {
    this.stop(`capture failed: ${exc.message}`);
    this.dispatchEvent(new CustomEvent("failure", { detail: exc }));
  }

  /** The image of frame seq (for the AR view), releasing the images of older frames. */
  takeImage(seq) {
    const bitmap = this.images.get(seq) ?? null;
    for (const [s, b] of this.images) {
      if (s < seq) {
        b?.close();
        this.images.delete(s);
      }
    }
    this.images.delete(seq);
    return bitmap;
  }

  /** Forget images of frames that an error answered (no pose will show them). */
  dropImagesUpTo(seq) {
    for (const [s, b] of this.images) {
      if (s <= seq) {
        b?.close();
        this.images.delete(s);
      }
    }
  }
}
