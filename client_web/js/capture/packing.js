// Frame packing for the live mode (and anything else that captures pixels): colour to JPEG,
// depth from metres to uint16 units and a zlib stream, intrinsics from a projection matrix.
// Pure functions of typed arrays, testable in any browser; conventions as shared/PROTOCOL.md:
// pixel centres at integer coordinates, camera x right, y down, z forward (OpenCV).

export const DEPTH_SCALE_MM = 1000; // depth units per metre: millimetres
const LITTLE_ENDIAN = new Uint8Array(new Uint16Array([1]).buffer)[0] === 1;

function canvasOf(width, height) {
  if (typeof OffscreenCanvas !== "undefined") return new OffscreenCanvas(width, height);
  const canvas = document.createElement("canvas");
  canvas.width = width;
  canvas.height = height;
  return canvas;
}

async function canvasToBlob(canvas, type, quality) {
  if (canvas.convertToBlob) return canvas.convertToBlob({ type, quality });
  return new Promise((resolve, reject) =>
    canvas.toBlob((b) => (b ? resolve(b) : reject(new Error("canvas.toBlob failed"))), type, quality));
}

/**
 * Encode an image as a baseline JPEG.
 * @param {ImageData|ImageBitmap|HTMLCanvasElement|OffscreenCanvas|HTMLImageElement} source
 * @param {number} quality 0..1 (0.8 as the protocol's bandwidth table)
 * @returns {Promise<Uint8Array>} the JPEG file's bytes (starts FF D8 FF, ends FF D9)
 */
export async function encodeJpeg(source, quality = 0.8) {
  const width = source.width;
  const height = source.height;
  const canvas = canvasOf(width, height);
  const ctx = canvas.getContext("2d");
  if (typeof ImageData !== "undefined" && source instanceof ImageData) ctx.putImageData(source, 0, 0);
  else ctx.drawImage(source, 0, 0, width, height);
  const blob = await canvasToBlob(canvas, "image/jpeg", quality);
  return new Uint8Array(await blob.arrayBuffer());
}

/** RGBA rows bottom-up (as WebGL's readPixels returns them) -> top-down, as a new array. */
export function flipRows(rgba, width, height) {
  const out = new Uint8ClampedArray(rgba.length);
  const row = width * 4;
  for (let y = 0; y < height; y++) out.set(rgba.subarray((height - 1 - y) * row, (height - y) * row), y * row);
  return out;
}

/**
 * Depth samples to uint16 units: round(value * rawValueToMeters * depthScale).
 * Not finite, not positive or beyond the uint16 range (65.535 m at millimetres) -> 0, "no
 * measurement", rather than a clamped, wrong distance.
 * @param {Float32Array|Uint16Array|number[]} values raw depth (WebXR: float32 or luminance-alpha)
 * @param {{rawValueToMeters?: number, depthScale?: number}} options
 * @returns {Uint16Array}
 */
export function depthToUint16(values, { rawValueToMeters = 1, depthScale = DEPTH_SCALE_MM } = {}) {
  const out = new Uint16Array(values.length);
  const k = rawValueToMeters * depthScale;
  for (let i = 0; i < values.length; i++) {
    const units = Math.round(values[i] * k);
    out[i] = units > 0 && units <= 65535 ? units : 0; // NaN compares false: 0
  }
  return out;
}

/** The little-endian bytes of a uint16 array (a view when the machine is little-endian). */
export function uint16LittleEndian(u16) {
  const bytes = new Uint8Array(u16.buffer, u16.byteOffset, u16.byteLength);
  if (LITTLE_ENDIAN) return bytes;
  const out = new Uint8Array(bytes.length);
  for (let i = 0; i < bytes.length; i += 2) [out[i], out[i + 1]] = [bytes[i + 1], bytes[i]];
  return out;
}

async function pipeBytes(bytes, transform) {
  const stream = new Blob([bytes]).stream().pipeThrough(transform);
  return new Uint8Array(await new Response(stream).arrayBuffer());
}

/** One zlib stream (RFC 1950: header, deflate, Adler-32): CompressionStream's "deflate". */
export function zlibCompress(bytes) {
  return pipeBytes(bytes, new CompressionStream("deflate"));
}

export function zlibDecompress(bytes) {
  return pipeBytes(bytes, new DecompressionStream("deflate"));
}

/**
 * Depth for a frame message: metres (or raw values) -> uint16 units -> zlib.
 * @returns {Promise<{depth: Uint8Array, depthFormat: "zlib", depthScale: number}>}
 */
export async function packDepth(values, { rawValueToMeters = 1, depthScale = DEPTH_SCALE_MM } = {}) {
  const units = depthToUint16(values, { rawValueToMeters, depthScale });
  return { depth: await zlibCompress(uint16LittleEndian(units)), depthFormat: "zlib", depthScale };
}

/**
 * Resample a depth buffer onto the view's pixel grid (nearest neighbour), through WebXR's
 * normDepthBufferFromNormView: normalized view coordinates (0..1, x right, y down, origin top
 * left) -> normalized depth-buffer coordinates. Handles the rotated buffers of portrait phones.
 * @param {Float32Array|Uint16Array} src row-major, srcW x srcH
 * @param {Float32Array|number[]|null} matrix 4x4 column-major (XRRigidTransform.matrix); null: identity
 * @returns same type as src, outW x outH, 0 where the view sees outside the buffer
 */
export function resampleDepth(src, srcW, srcH, outW, outH, matrix = null) {
  const m = matrix ?? [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1];
  const out = new src.constructor(outW * outH);
  for (let y = 0; y < outH; y++) {
    const v = (y + 0.5) / outH;
    for (let x = 0; x < outW; x++) {
      const u = (x + 0.5) / outW;
      const w = m[3] * u + m[7] * v + m[15] || 1;
      const du = (m[0] * u + m[4] * v + m[12]) / w;
      const dv = (m[1] * u + m[5] * v + m[13]) / w;
      const sx = Math.floor(du * srcW);
      const sy = Math.floor(dv * srcH);
      if (sx >= 0 && sx < srcW && sy >= 0 && sy < srcH) out[y * outW + x] = src[sy * srcW + sx];
    }
  }
  return out;
}

/** The depth image size (w, h) to send for a depth buffer of n1 x n2 samples: the colour
 * image's aspect ratio (the protocol requires it: same field of view), with the buffer's longer
 * side along the colour's longer side. A phone's depth buffer often has another aspect than its
 * screen (ARCore: 160x90 landscape for a 1080x2400 portrait view); resampleDepth fills it
 * through normDepthBufferFromNormView. */
export function depthSizeFor(colourSize, n1, n2) {
  const [cw, ch] = colourSize;
  const long = Math.max(n1, n2);
  return cw >= ch ? [long, Math.max(1, Math.round((long * ch) / cw))] : [Math.max(1, Math.round((long * cw) / ch)), long];
}

/**
 * Pinhole intrinsics [fx, fy, cx, cy] (pixels, OpenCV: pixel centres at integers, y down) of a
 * WebGL/WebXR projection matrix (column-major, camera looking down -z, y up) on a viewport of
 * width x height pixels. Inverse of projectionFromIntrinsics.
 */
export function intrinsicsFromProjection(p, width, height) {
  const fx = (p[0] * width) / 2;
  const fy = (p[5] * height) / 2;
  const cx = ((1 - p[8]) * width) / 2 - 0.5;
  const cy = ((1 + p[9]) * height) / 2 - 0.5;
  return [fx, fy, cx, cy];
}

/** The column-major OpenGL projection matrix of pinhole intrinsics on a width x height image:
 * what a three.js camera needs to draw over that image exactly. */
export function projectionFromIntrinsics([fx, fy, cx, cy], width, height, near = 0.05, far = 100) {
  const p = new Float32Array(16);
  p[0] = (2 * fx) / width;
  p[5] = (2 * fy) / height;
  p[8] = 1 - (2 * cx + 1) / width;
  p[9] = (2 * cy + 1) / height - 1;
  p[10] = -(far + near) / (far - near);
  p[11] = -1;
  p[14] = (-2 * far * near) / (far - near);
  return p;
}

/** Intrinsics of the same camera on an image resized from `from` to `to` ([w, h], pixels),
 * with pixel centres at integer coordinates (as protocol.depth_intrinsics). */
export function scaleIntrinsics([fx, fy, cx, cy], from, to) {
  const sx = to[0] / from[0];
  const sy = to[1] / from[1];
  return [fx * sx, fy * sy, (cx + 0.5) * sx - 0.5, (cy + 0.5) * sy - 0.5];
}

/**
 * The frame message's T_device_camera from a WebXR view pose: the camera-to-space matrix of a GL
 * camera (x right, y up, z backward), column-major, times diag(1, -1, -1, 1) on the right for
 * this protocol's camera axes (x right, y down, z forward), written row-major.
 * @param {Float32Array|number[]} cameraToSpace XRView.transform.matrix
 * @returns {number[]} 16 numbers, row-major, metres
 */
export function deviceCameraFromView(cameraToSpace) {
  const out = new Array(16);
  for (let r = 0; r < 4; r++) {
    for (let c = 0; c < 4; c++) out[r * 4 + c] = cameraToSpace[c * 4 + r] * (c === 1 || c === 2 ? -1 : 1);
  }
  return out;
}

/**
 * Gravity in the camera frame (OpenCV axes), for the hello, from a WebXR view pose in a
 * gravity-aligned reference space (y up, as ARCore's "local" space).
 * @param {Float32Array|number[]} cameraToSpace column-major 4x4 (XRView.transform.matrix: a GL
 *   camera, x right, y up, z backward)
 * @returns {number[]} unit vector [gx, gy, gz]; camera upright and level gives [0, 1, 0]
 */
export function gravityInCamera(cameraToSpace) {
  const m = cameraToSpace;
  // R^T * (0, -1, 0): minus the second row of R, i.e. minus the y component of each axis.
  const gl = [-m[1], -m[5], -m[9]];
  const cv = [gl[0], -gl[1], -gl[2]]; // GL camera (y up, z back) -> OpenCV (y down, z forward)
  const n = Math.hypot(...cv) || 1;
  return cv.map((v) => v / n);
}
