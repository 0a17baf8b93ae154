// A worker that reads replayed frames' depth PNGs for occlusion (frame_depths.js) off the main
// thread, where the stream's sends and poses are handled: {id, bytes, depthScale} in,
// {id, width, height, metres} (Float32Array, transferred) or {id, error} out.

import { decodeDepthPng, depthMetres } from "../formats/depth_png.js";

self.onmessage = async ({ data: { id, bytes, depthScale } }) => {
  try {
    const { width, height, values } = await decodeDepthPng(bytes);
    const metres = depthMetres(values, depthScale);
    self.postMessage({ id, width, height, metres }, [metres.buffer]);
  } catch (exc) {
    self.postMessage({ id, error: exc.message });
  }
};
