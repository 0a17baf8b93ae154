// Frames and transforms between the protocol (row-major 4x4 lists, OpenCV camera: x right,
// y down, z forward) and three.js (column-major Matrix4, camera looking down -z with y up).

import * as THREE from "three";

/** A protocol transform (16 floats, row-major, metres) as a THREE.Matrix4. */
export function matrixFromRowMajor(values) {
  const m = new THREE.Matrix4();
  m.set(...values); // Matrix4.set takes its arguments row by row
  return m;
}

/** OpenCV camera frame -> three.js camera frame: flip y and z. Its own inverse. */
export const CV_TO_GL = Object.freeze(new THREE.Matrix4().makeScale(1, -1, -1));

/** World "up" as a unit vector: against gravity (the hello's, in the first camera's frame, which
 * is the world frame), else the first camera's -y (held upright). */
export function upFromGravity(gravity) {
  if (gravity && Math.hypot(...gravity) > 1e-9) return new THREE.Vector3(...gravity).normalize().negate();
  return new THREE.Vector3(0, -1, 0);
}

/** Flat [x0, y0, z0, x1, ...] -> THREE.Vector3 list. */
export function pointsFromFlat(flat) {
  const points = [];
  for (let i = 0; i + 2 < flat.length; i += 3) points.push(new THREE.Vector3(flat[i], flat[i + 1], flat[i + 2]));
  return points;
}

/** Pixel (u, v) of a camera-frame point (OpenCV) through intrinsics; null behind the camera. */
export function projectPoint([fx, fy, cx, cy], [x, y, z]) {
  if (!(z > 1e-6)) return null;
  return [fx * (x / z) + cx, fy * (y / z) + cy];
}

/** Heat-map colour (Google's Turbo, polynomial fit) of t in [0, 1] -> [r, g, b] in [0, 1]. */
export function turbo(t) {
  const x = Math.min(1, Math.max(0, t));
  const r = 0.13572138 + x * (4.6153926 + x * (-42.66032258 + x * (132.13108234 + x * (-152.94239396 + x * 59.28637943))));
  const g = 0.09140261 + x * (2.19418839 + x * (4.84296658 + x * (-14.18503333 + x * (4.27729857 + x * 2.82956604))));
  const b = 0.1066733 + x * (12.64194608 + x * (-60.58204836 + x * (110.36276771 + x * (-89.90310912 + x * 27.34824973))));
  return [Math.min(1, Math.max(0, r)), Math.min(1, Math.max(0, g)), Math.min(1, Math.max(0, b))];
}
