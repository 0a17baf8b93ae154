// The depth of the frames a replay sent, kept until the frame is shown, for occlusion in the AR
// view (occlusion.js): the depth PNG is decoded when the frame goes out, so that it is ready by
// the time its pose comes back and the AR view shows the frame. Live capture needs none of this:
// its overlay is drawn over the current XR frame, whose own depth capture/sources/live.js hands over.
// The PNG is read in a worker (depth_worker.js) where the browser has module workers, so that
// the main thread, which sends the frames and handles their poses, only fills the depth's holes.

import { decodeDepthPng, depthMetres } from "../formats/depth_png.js";

const KEPT = 8; // frames in flight are at most max_in_flight (2); a few more for late poses

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
    this.pending = new Map(); // seq -> Promise<{metres, width, height}|null>
    this.failures = 0;
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
    const worker = this.worker && !this.worker.broken ? this.worker : null;
    const decoded = (worker ? worker.decode(fields.depth, fields.depthScale) : decodeHere(fields.depth, fields.depthScale))
      .catch((exc) => {
        this.failures += 1;
        console.warn("depth for occlusion could not be read", exc.message);
        return null;
      });
    this.pending.set(seq, decoded);
    for (const key of this.pending.keys()) if (this.pending.size > KEPT) this.pending.delete(key);
  }

  /** Frame seq is on screen now: its depth goes to the occluder once decoded (if still shown). */
  shown(seq) {
    const decoded = this.pending.get(seq);
    for (const key of this.pending.keys()) if (key <= seq) this.pending.delete(key);
    decoded?.then((depth) => {
      const ar = this.arView;
      if (!depth || ar.frame?.seq !== seq) return;
      ar.occlusion.setDepth(depth.metres, depth.width, depth.height, seq);
      ar.dirty = true;
    });
  }
}
