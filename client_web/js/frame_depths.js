// The depth of the frames a replay sent, kept until the frame is shown, for occlusion in the AR
// view (occlusion.js): the depth PNG is decoded when the frame goes out, so that it is ready by
// the time its pose comes back and the AR view shows the frame. Live capture needs none of this:
// its overlay is drawn over the current XR frame, whose own depth sources/live.js hands over.

import { decodeDepthPng, depthMetres } from "./depth_png.js";

const KEPT = 8; // frames in flight are at most max_in_flight (2); a few more for late poses

export class FrameDepths {
  /** @param {import("./ar_view.js").ARView} arView */
  constructor(arView) {
    this.arView = arView;
    this.pending = new Map(); // seq -> Promise<{metres, width, height}|null>
    this.failures = 0;
  }

  /** A frame went out with these message fields (depth, depthFormat, depthScale). */
  keep(seq, fields) {
    if (!this.arView.occlusion.enabled || fields?.depthFormat !== "png") return;
    const decoded = decodeDepthPng(fields.depth)
      .then(({ width, height, values }) => ({ width, height, metres: depthMetres(values, fields.depthScale) }))
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
