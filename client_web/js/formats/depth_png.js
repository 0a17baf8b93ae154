// Depth images for the page itself: a replayed frame's depth is a 16-bit greyscale PNG (TUM
// layout, as the demo and uploaded recordings send it), which the browser's image decoders
// would cut to 8 bits. This reads the PNG's samples as they are: the IDAT chunks are one zlib
// stream (inflated with DecompressionStream), then each row's filter is undone (PNG spec,
// section 9). Only what depth images use: 16-bit greyscale, not interlaced.

import { zlibDecompress } from "../capture/packing.js";

const SIGNATURE = [0x89, 0x50, 0x4e, 0x47, 0x0d, 0x0a, 0x1a, 0x0a];

/** Paeth predictor (PNG filter type 4). */
function paeth(a, b, c) {
  const p = a + b - c;
  const pa = Math.abs(p - a);
  const pb = Math.abs(p - b);
  const pc = Math.abs(p - c);
  if (pa <= pb && pa <= pc) return a;
  return pb <= pc ? b : c;
}

/**
 * The samples of a 16-bit greyscale PNG.
 * @param {Uint8Array} bytes the PNG file
 * @returns {Promise<{width: number, height: number, values: Uint16Array}>} row-major, top row first
 */
export async function decodeDepthPng(bytes) {
  if (bytes.length < 33 || !SIGNATURE.every((b, i) => bytes[i] === b)) throw new Error("not a PNG file");
  const view = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
  const width = view.getUint32(16);
  const height = view.getUint32(20);
  const [bitDepth, colourType, , , interlace] = bytes.subarray(24, 29);
  if (bitDepth !== 16 || colourType !== 0 || interlace !== 0) {
    throw new Error(`depth PNG must be 16-bit greyscale, not interlaced (got bit depth ${bitDepth}, colour type ${colourType})`);
  }
  const parts = [];
  for (let at = 8; at + 8 <= bytes.length;) {
    const length = view.getUint32(at);
    const type = String.fromCharCode(...bytes.subarray(at + 4, at + 8));
    if (type === "IDAT") parts.push(bytes.subarray(at + 8, at + 8 + length));
    if (type === "IEND") break;
    at += 12 + length;
  }
  const stream = new Uint8Array(parts.reduce((n, p) => n + p.length, 0));
  parts.reduce((offset, p) => (stream.set(p, offset), offset + p.length), 0);
  const raw = await zlibDecompress(stream);
  const stride = width * 2;
  if (raw.length < height * (stride + 1)) throw new Error("the depth PNG is truncated");
  const rows = new Uint8Array(height * stride);
  for (let y = 0; y < height; y++) {
    const filter = raw[y * (stride + 1)];
    const src = raw.subarray(y * (stride + 1) + 1, (y + 1) * (stride + 1));
    const out = rows.subarray(y * stride, (y + 1) * stride);
    const up = y > 0 ? rows.subarray((y - 1) * stride, y * stride) : null;
    if (filter > 4) throw new Error(`unknown PNG filter ${filter} in row ${y}`);
    for (let x = 0; x < stride; x++) {
      const a = x >= 2 ? out[x - 2] : 0; // the same byte of the sample to the left (2 bytes per sample)
      const b = up ? up[x] : 0;
      let predictor = 0;
      if (filter === 1) predictor = a;
      else if (filter === 2) predictor = b;
      else if (filter === 3) predictor = (a + b) >> 1;
      else if (filter === 4) predictor = paeth(a, b, up && x >= 2 ? up[x - 2] : 0);
      out[x] = (src[x] + predictor) & 0xff;
    }
  }
  const values = new Uint16Array(width * height);
  for (let i = 0; i < values.length; i++) values[i] = (rows[2 * i] << 8) | rows[2 * i + 1]; // big-endian samples
  return { width, height, values };
}

/** Depth in metres (0: no measurement) of uint16 samples at depthScale units per metre. */
export function depthMetres(values, depthScale) {
  const metres = new Float32Array(values.length);
  for (let i = 0; i < values.length; i++) metres[i] = values[i] / depthScale;
  return metres;
}
