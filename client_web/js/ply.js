// Readers for the server's downloads, so that a page reopened into a running session shows the
// map and trajectory made so far (map_chunk messages only carry what is new): a binary PLY point
// cloud (x, y, z and red, green, blue per vertex, as Open3D writes it) and a TUM trajectory.

const PLY_TYPES = {
  char: ["getInt8", 1], int8: ["getInt8", 1], uchar: ["getUint8", 1], uint8: ["getUint8", 1],
  short: ["getInt16", 2], int16: ["getInt16", 2], ushort: ["getUint16", 2], uint16: ["getUint16", 2],
  int: ["getInt32", 4], int32: ["getInt32", 4], uint: ["getUint32", 4], uint32: ["getUint32", 4],
  float: ["getFloat32", 4], float32: ["getFloat32", 4], double: ["getFloat64", 8], float64: ["getFloat64", 8],
};

/**
 * Vertices of a binary little-endian PLY file.
 * @param {ArrayBuffer} buffer
 * @returns {{points: Float32Array, colours: Uint8Array}} xyz (metres) and rgb per vertex
 */
export function parsePly(buffer) {
  const bytes = new Uint8Array(buffer);
  const headerEnd = findHeaderEnd(bytes);
  const header = new TextDecoder().decode(bytes.subarray(0, headerEnd)).split(/\r?\n/);
  if (header[0] !== "ply") throw new Error("not a PLY file");
  if (!header.includes("format binary_little_endian 1.0")) throw new Error("only binary little-endian PLY is read");
  const elements = [];
  for (const line of header) {
    const [word, ...rest] = line.trim().split(/\s+/);
    if (word === "element") elements.push({ name: rest[0], count: Number(rest[1]), properties: [] });
    else if (word === "property") {
      if (rest[0] === "list") throw new Error("PLY lists are not read (a mesh?): need a point cloud");
      const type = PLY_TYPES[rest[0]];
      if (!type) throw new Error(`unknown PLY property type ${rest[0]}`);
      elements.at(-1).properties.push({ name: rest[1], read: type[0], size: type[1] });
    }
  }
  const vertex = elements[0];
  if (!vertex || vertex.name !== "vertex") throw new Error("the PLY file has no vertices first");
  let stride = 0;
  const offsets = {};
  for (const p of vertex.properties) {
    offsets[p.name] = { offset: stride, read: p.read };
    stride += p.size;
  }
  for (const name of ["x", "y", "z"]) if (!offsets[name]) throw new Error(`the PLY vertices have no ${name}`);
  const view = new DataView(buffer, headerEnd);
  if (view.byteLength < stride * vertex.count) throw new Error("the PLY file is truncated");
  const points = new Float32Array(vertex.count * 3);
  const colours = new Uint8Array(vertex.count * 3).fill(200);
  const channels = ["red", "green", "blue"].map((c) => offsets[c]);
  for (let i = 0; i < vertex.count; i++) {
    const base = i * stride;
    ["x", "y", "z"].forEach((name, k) => {
      const { offset, read } = offsets[name];
      points[3 * i + k] = view[read](base + offset, true);
    });
    channels.forEach((c, k) => {
      if (c) colours[3 * i + k] = view[c.read](base + c.offset, true);
    });
  }
  return { points, colours };
}

function findHeaderEnd(bytes) {
  const marker = new TextEncoder().encode("end_header");
  const limit = Math.min(bytes.length, 65536);
  for (let i = 0; i + marker.length < limit; i++) {
    if (marker.every((b, k) => bytes[i + k] === b)) {
      let end = i + marker.length;
      if (bytes[end] === 0x0d) end += 1;
      if (bytes[end] === 0x0a) return end + 1;
    }
  }
  throw new Error("no PLY header");
}

/** Camera positions [x, y, z] (metres) of a TUM trajectory ("t tx ty tz qx qy qz qw" lines). */
export function parseTumPositions(text) {
  const positions = [];
  for (const line of text.split(/\r?\n/)) {
    if (!line.trim() || line.startsWith("#")) continue;
    const v = line.trim().split(/\s+/).map(Number);
    if (v.length >= 8 && v.every(Number.isFinite)) positions.push([v[1], v[2], v[3]]);
  }
  return positions;
}
