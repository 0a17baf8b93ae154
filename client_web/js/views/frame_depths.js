// The depth of the frames a replay sent, kept until the frame is shown, for occlusion in the AR
// view (occlusion.js). Where the view draws about as often as frames come, the depth PNG is
// decoded when the frame goes out, so that it is ready by the time its pose comes back and the
// view shows the frame. Where it draws less often (a slow page: render_budget.js), most frames
// are replaced on screen before any draw shows them, and their depth is wasted work on the CPU
// the stream needs: then only the frame shown last before a draw is read, just before that
// draw is due. Live capture needs none of this: its overlay is drawn over the current XR frame,
// whose own depth capture/sources/live.js hands over. The PNG is read in a worker
// (depth_worker.js) where the browser has module workers, so that the main thread, which sends
// the frames and handles their poses, only fills the depth's holes.

import { decodeDepthPng, depthMetres } from "../formats/depth_png.js";

const KEPT = 8; // frames in flight are at most max_in_flight (2); a few more for late poses
const EAGER_DRAW_MS = 70; // draws at most this far apart (15 fps frames): every frame's depth is read
const READ_LEAD_MS = 40; // otherwise the shown frame's depth is read this long before the next draw

/** Depth PNGs read by a worker: decode(bytes, depthScale) -> Promise<{width, height, metres}>. */
class DepthWorker {
  constructor() {
    this.worker = new Worker(new URL("./depth_worker.js", import.meta.url), { type: "module" });
    this.waiting = new Map(); // id -> {resolve, reject}
    this.nextId = 0;
    this.worker.onmessage = ({ data }) => {
      const promise = this.waiting.get(data.id);
      this.waiting.delete(data.id);
      if (data.error) promise?.reject(new Error(data.error));
      else promise?.resolve(data);
    };
    this.worker.onerror = (event) => {
      event.preventDefault?.();
      for (const { reject } of this.waiting.values()) reject(new Error(`the depth worker failed: ${event.message}`));
      this.waiting.clear();
      this.broken = true;
    };
  }

  decode(bytes, depthScale) {
    const id = this.nextId++;
    return new Promise((resolve, reject) => {
      this.waiting.set(id, { resolve, reject });
      this.worker.postMessage({ id, bytes, depthScale }); // a copy: the frame keeps its bytes
    });
  }
}

/** The depth in metres of a 16-bit PNG on this thread (no worker). */
async function decodeHere(bytes, depthScale) {
  const { width, height, values } = await decodeDepthPng(bytes);
  return { width, height, metres: depthMetres(values, depthScale) };
}

export class FrameDepths {
  /** @param {import("./ar_view.js").ARView} arView */
  constructor(arView) {
    this.arView = arView;
    this.pending = new Map(); // seq -> {fields, decoded: Promise<{metres, width, height}|null>|null}
    this.failures = 0;
    this.reads = 0; // depth PNGs decoded (lazily: fewer than the frames shown)
    this.timer = null;
    try {
      this.worker = typeof Worker === "undefined" ? null : new DepthWorker();
    } catch {
      this.worker = null; // no module workers: read on the main thread
    }
  }

  /** A frame is shown when its pose comes (the session state's "pose", session/state.js). */
  follow(state) {
    state.addEventListener("pose", ({ detail: pose }) => this.shown(pose.seq));
  }

  /** A frame went out with these message fields (depth, depthFormat, depthScale). */
  keep(seq, fields) {
    if (!this.arView.occlusion.enabled || fields?.depthFormat !== "png") return;
    const eager = (this.arView.budget?.drawIntervalMs ?? 0) <= EAGER_DRAW_MS;
    this.pending.set(seq, { fields, decoded: eager ? this.#read(fields) : null });
    for (const key of this.pending.keys()) if (this.pending.size > KEPT) this.pending.delete(key);
  }

  /** Frame seq is on screen now: its depth goes to the occluder once decoded (if still shown). */
  shown(seq) {
    const kept = this.pending.get(seq);
    for (const key of this.pending.keys()) if (key <= seq) this.pending.delete(key);
    if (!kept) return;
    clearTimeout(this.timer); // a frame shown earlier and not yet read is replaced: not read
    if (kept.decoded) {
      this.#apply(seq, kept.decoded);
      return;
    }
    const ar = this.arView;
    const due = ar.lastRender + (ar.budget?.drawIntervalMs ?? 0);
    const wait = Math.max(0, due - READ_LEAD_MS - performance.now());
    this.timer = setTimeout(() => this.#apply(seq, this.#read(kept.fields)), wait);
  }

  /** A frame's depth PNG decoded to metres (null when it cannot be read: counted). */
  #read(fields) {
    this.reads += 1;
    const worker = this.worker && !this.worker.broken ? this.worker : null;
    return (worker ? worker.decode(fields.depth, fields.depthScale) : decodeHere(fields.depth, fields.depthScale))
      .catch((exc) => {
        this.failures += 1;
        console.warn("depth for occlusion could not be read", exc.message);
        return null;
      });
  }

  #apply(seq, decoded) {
    decoded.then((depth) => {
      const ar = this.arView;
      if (!depth || ar.frame?.seq !== seq) return;
      ar.occlusion.setDepth(depth.metres, depth.width, depth.height, seq);
      ar.dirty = true;
    });
  }
}
