// Replay source: an RGB-D sequence streamed as if a camera captured it now. Frames come from
// the server's bundled demo (/api/demo), from an iPhone recording uploaded to the server
// (/api/recordings: Stray Scanner or Record3D, converted there), or from a TUM-layout folder the
// user picks (rgb.txt, depth.txt, optional intrinsics.json). Colour goes out as JPEG (a PNG
// colour image is re-encoded), depth as the sequence's 16-bit PNG with its depth scale, and a
// recording's own phone pose as T_device_camera.

import { encodeJpeg } from "../packing.js";

const PREFETCH = 4; // frames loaded (and their colour decoded) ahead of the one being captured
const TUM_INTRINSICS = { // factory calibration of the TUM Kinects, 640x480 (as server/datasets/tum.py)
  fr1: [517.3, 516.5, 318.6, 255.3],
  fr2: [520.9, 521.0, 325.1, 249.7],
  fr3: [535.4, 539.2, 320.1, 247.6],
};
const MAX_ASSOCIATION_S = 0.02;

/** Width, height, bit depth and colour type of a PNG file's header, or null. */
export function pngHeader(bytes) {
  const signature = [0x89, 0x50, 0x4e, 0x47, 0x0d, 0x0a, 0x1a, 0x0a];
  if (bytes.length < 26 || !signature.every((b, i) => bytes[i] === b)) return null;
  const view = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
  return { width: view.getUint32(16), height: view.getUint32(20), bitDepth: bytes[24], colourType: bytes[25] };
}

const isJpeg = (bytes) => bytes[0] === 0xff && bytes[1] === 0xd8 && bytes[2] === 0xff;

/** Parse a TUM ``timestamp filename`` list -> [{t, name}], skipping comments. */
export function parseFileList(text, what) {
  const rows = [];
  text.split(/\r?\n/).forEach((raw, i) => {
    const line = raw.trim();
    if (!line || line.startsWith("#")) return;
    const [t, name] = line.replace(/,/g, " ").split(/\s+/);
    if (!name || !Number.isFinite(Number(t))) throw new Error(`${what} line ${i + 1}: expected 'timestamp filename', got '${line}'`);
    rows.push({ t: Number(t), name });
  });
  if (!rows.length) throw new Error(`${what} lists no images`);
  return rows;
}

/** Nearest-timestamp association of colour and depth rows within MAX_ASSOCIATION_S, one-to-one. */
export function associate(rgb, depth) {
  const sorted = [...depth].sort((a, b) => a.t - b.t);
  const used = new Set();
  const pairs = [];
  let j = 0;
  for (const c of [...rgb].sort((a, b) => a.t - b.t)) {
    while (j + 1 < sorted.length && sorted[j + 1].t <= c.t) j++;
    const candidates = [sorted[j], sorted[j + 1]].filter((d) => d && !used.has(d));
    const best = candidates.sort((a, b) => Math.abs(a.t - c.t) - Math.abs(b.t - c.t))[0];
    if (best && Math.abs(best.t - c.t) <= MAX_ASSOCIATION_S) {
      used.add(best);
      pairs.push({ timestamp: c.t, colour: c.name, depth: best.name });
    }
  }
  return pairs;
}

/** A sequence: camera, sizes, depth scale, and a loader of frame i's files. */
export class ReplaySequence {
  constructor({ name, intrinsics, colourSize, depthSize, depthScale, gravity = null, fps, frames, read }) {
    Object.assign(this, { name, intrinsics, colourSize, depthSize, depthScale, gravity, fps, frames, read });
  }

  get length() {
    return this.frames.length;
  }

  /** A sequence the server serves: the bundled demo (generated on the server's first use: may
   * take a while), or an uploaded recording, whose index and files need its token. */
  static async fromServer(url = "/api/demo", { token = null } = {}) {
    const headers = token ? { Authorization: `Bearer ${token}` } : {};
    const response = await fetch(url, { headers });
    if (!response.ok) throw new Error(`cannot load the sequence ${url}: HTTP ${response.status}`);
    const index = await response.json();
    const get = async (path) => {
      const r = await fetch(path, { headers });
      if (!r.ok) throw new Error(`${path}: HTTP ${r.status}`);
      return new Uint8Array(await r.arrayBuffer());
    };
    return new ReplaySequence({
      name: index.name, intrinsics: index.intrinsics, colourSize: index.colour_size, depthSize: index.depth_size,
      depthScale: index.depth_scale, gravity: index.gravity, fps: index.fps, frames: index.frames,
      read: async (frame) => Promise.all([get(frame.colour), get(frame.depth)]),
    });
  }

  /**
   * An iPhone recording (a Record3D .r3d, or a Stray Scanner export zipped) uploaded to the
   * server, which converts it; then read back like the demo. XMLHttpRequest, as fetch cannot
   * report an upload's progress.
   * @param {File} file
   * @param {(stage: "upload"|"convert", fraction: number) => void} onProgress
   */
  static async fromUpload(file, onProgress = () => {}) {
    const created = await new Promise((resolve, reject) => {
      const xhr = new XMLHttpRequest();
      xhr.open("POST", `/api/recordings?name=${encodeURIComponent(file.name)}`);
      xhr.setRequestHeader("Content-Type", "application/octet-stream");
      xhr.responseType = "json";
      xhr.upload.onprogress = (e) => onProgress("upload", e.lengthComputable ? e.loaded / e.total : 0);
      xhr.upload.onload = () => onProgress("convert", 0);
      xhr.onload = () => {
        if (xhr.status === 201) resolve(xhr.response);
        else reject(new Error(`upload refused (HTTP ${xhr.status}): ${xhr.response?.error?.message ?? "no reason given"}`));
      };
      xhr.onerror = () => reject(new Error("upload failed: the connection broke"));
      xhr.send(file);
    });
    onProgress("convert", 1);
    return ReplaySequence.fromServer(created.index, { token: created.token });
  }

  /** A TUM-layout folder from an <input type=file webkitdirectory> (a FileList). */
  static async fromFiles(fileList) {
    const files = new Map();
    let folder = "sequence";
    for (const file of fileList) {
      const parts = (file.webkitRelativePath || file.name).split("/");
      if (parts.length > 1) folder = parts[0];
      files.set(parts.slice(parts.length > 1 ? 1 : 0).join("/"), file);
    }
    const text = async (name) => {
      const file = files.get(name);
      if (!file) throw new Error(`the folder has no ${name} (need a TUM RGB-D layout: rgb.txt, depth.txt)`);
      return file.text();
    };
    const frames = associate(parseFileList(await text("rgb.txt"), "rgb.txt"), parseFileList(await text("depth.txt"), "depth.txt"));
    if (!frames.length) throw new Error("no rgb and depth timestamps match within 20 ms");
    const bytes = async (name) => {
      const file = files.get(name);
      if (!file) throw new Error(`missing file ${name}`);
      return new Uint8Array(await file.arrayBuffer());
    };
    const [firstColour, firstDepth] = await Promise.all([bytes(frames[0].colour), bytes(frames[0].depth)]);
    const png = pngHeader(firstDepth);
    if (!png || png.bitDepth !== 16 || png.colourType !== 0) {
      throw new Error(`${frames[0].depth} is not a 16-bit greyscale PNG: depth must be uint16`);
    }
    const bitmap = await createImageBitmap(new Blob([firstColour]));
    const colourSize = [bitmap.width, bitmap.height];
    bitmap.close();
    let intrinsics;
    let depthScale = 5000;
    if (files.has("intrinsics.json")) {
      const k = JSON.parse(await text("intrinsics.json"));
      intrinsics = [k.fx, k.fy, k.cx, k.cy].map(Number);
      if (k.depth_scale) depthScale = Number(k.depth_scale);
      if (k.width && (k.width !== colourSize[0] || k.height !== colourSize[1])) {
        throw new Error(`intrinsics.json says ${k.width}x${k.height} but the images are ${colourSize.join("x")}`);
      }
    } else {
      const match = /(?:fr|freiburg)([123])/.exec(folder.toLowerCase());
      if (!match) throw new Error("no intrinsics.json, and the folder name names no TUM camera (fr1/fr2/fr3)");
      intrinsics = TUM_INTRINSICS[`fr${match[1]}`];
    }
    const span = frames.at(-1).timestamp - frames[0].timestamp;
    const encodeColour = async (data) => (isJpeg(data) ? data : encodeJpeg(await createImageBitmap(new Blob([data])), 0.9));
    return new ReplaySequence({
      name: folder, intrinsics, colourSize, depthSize: [png.width, png.height], depthScale, gravity: null,
      fps: frames.length > 1 && span > 0 ? (frames.length - 1) / span : 15, frames,
      read: async (frame) => Promise.all([bytes(frame.colour).then(encodeColour), bytes(frame.depth)]),
    });
  }
}

/** Streams a ReplaySequence like a camera: capture(tick) gives the frame due at that tick;
 * playback runs forward and back (ping-pong), so the camera never jumps. */
export class ReplaySource {
  constructor(sequence, { loop = true } = {}) {
    this.kind = "replay";
    this.sequence = sequence;
    this.loop = loop;
    this.cache = new Map(); // frame index -> Promise<[colour, depth, ImageBitmap]>
  }

  get info() {
    const s = this.sequence;
    return {
      clientName: `web/1.0 replay ${s.name}`.slice(0, 64), intrinsics: s.intrinsics, colourSize: s.colourSize,
      depthSize: s.depthSize, depthScale: s.depthScale, gravity: s.gravity ?? undefined,
    };
  }

  /** Sequence index at a tick, or null after the end when not looping. */
  indexAt(tick) {
    const n = this.sequence.length;
    if (!this.loop) return tick < n ? tick : null;
    if (n === 1) return 0;
    const period = 2 * (n - 1);
    const k = tick % period;
    return k < n ? k : period - k;
  }

  /** Frame index's files and its colour decoded for the AR view: decoding ahead, while the
   * previous frame is with the server, means a captured frame goes out at once. */
  #load(index) {
    if (!this.cache.has(index)) {
      const promise = this.sequence.read(this.sequence.frames[index]).then(async ([colour, depth]) =>
        [colour, depth, await createImageBitmap(new Blob([colour], { type: "image/jpeg" }))]);
      promise.catch(() => this.cache.delete(index));
      this.cache.set(index, promise);
    }
    return this.cache.get(index);
  }

  /** Warm the cache around a tick (frames due soon). */
  prefetch(tick) {
    const keep = new Set();
    for (let k = 0; k <= PREFETCH; k++) {
      const index = this.indexAt(tick + k);
      if (index === null) break;
      keep.add(index);
      this.#load(index);
    }
    for (const [index, promise] of this.cache) {
      if (keep.has(index)) continue;
      this.cache.delete(index);
      promise.then(([, , bitmap]) => bitmap.close(), () => {});
    }
  }

  /**
   * The frame captured at `tick`: message fields and an ImageBitmap to show.
   * @returns {Promise<{fields: object, bitmap: ImageBitmap, index: number}|null>} null at the end
   */
  async capture(tick, timestamp) {
    const index = this.indexAt(tick);
    if (index === null) return null;
    const [colour, depth, bitmap] = await this.#load(index);
    this.cache.delete(index); // the bitmap is the AR view's now (it closes it once shown)
    this.prefetch(tick + 1);
    const fields = { timestamp, colour, depth, depthFormat: "png", depthScale: this.sequence.depthScale };
    // A phone's recording carries the phone's own pose: the server's tracker starts from it.
    const pose = this.sequence.frames[index].T_device_camera;
    if (pose) fields.deviceCamera = pose;
    return { index, bitmap, fields };
  }

  stop() {
    for (const promise of this.cache.values()) promise.then(([, , bitmap]) => bitmap.close(), () => {});
    this.cache.clear();
  }
}
