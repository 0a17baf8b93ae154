// What live AR asks of a WebXR session, in one place: the live source requests it
// (sources/live.js) and the device check page (/check) judges a phone against it. No three.js
// here, so the check page loads without it.

/** WebXR depth-sensing preferences: depth read on the CPU, as uint16 millimetres (Chrome on
 * ARCore: luminance-alpha, newer unsigned-short) or float32 metres. */
export const LIVE_DEPTH_SENSING = Object.freeze({
  usagePreference: Object.freeze(["cpu-optimized"]),
  dataFormatPreference: Object.freeze(["luminance-alpha", "unsigned-short", "float32"]),
});
