// Reader for the server's fused surface (GET /api/sessions/{id}/mesh.ply, as Open3D writes it):
// a binary little-endian PLY with a `vertex` element (x, y, z, optional normals and
// red, green, blue) and a `face` element whose vertex_indices is a list (a count, then that
// many indices). Faces with more than three corners are fanned into triangles.

const TYPES = {
  char: ["getInt8", 1], int8: ["getInt8", 1], uchar: ["getUint8", 1], uint8: ["getUint8", 1],
  short: ["getInt16", 2], int16: ["getInt16", 2], ushort: ["getUint16", 2], uint16: ["getUint16", 2],
  int: ["getInt32", 4], int32: ["getInt32", 4], uint: ["getUint32", 4], uint32: ["getUint32", 4],
  float: ["getFloat32", 4], float32: ["getFloat32", 4], double: ["getFloat64", 8], float64: ["getFloat64", 8],
};

function headerOf(bytes) {
  const marker = new TextEncoder().encode("end_header\n");
  const limit = Math.min(bytes.length, 65536);
  for (let i = 0; i + marker.length <= limit; i++) {
    if (marker.every((b, k) => bytes[i + k] === b)) return i + marker.length;
  }
  throw new Error("no PLY header");
}

function typeOf(name) {
  const type = TYPES[name];
  if (!type) throw new Error(`unknown PLY property type ${name}`);
  return type;
}

/**
 * A triangle mesh from a binary little-endian PLY file.
 * @param {ArrayBuffer} buffer
 * @returns {{positions: Float32Array, colours: Uint8Array, indices: Uint32Array}} xyz in metres
 *   (world frame), rgb per vertex (200 grey when the file has none), three indices per triangle
 */
export function parseMeshPly(buffer) {
  const bytes = new Uint8Array(buffer);
  const end = headerOf(bytes);
  const lines = new TextDecoder().decode(bytes.subarray(0, end)).split("\n").map((l) => l.trim());
  if (lines[0] !== "ply") throw new Error("not a PLY file");
  if (!lines.includes("format binary_little_endian 1.0")) throw new Error("only binary little-endian PLY is read");
  const elements = [];
  for (const line of lines) {
    const [word, ...rest] = line.split(/\s+/);
    if (word === "element") elements.push({ name: rest[0], count: Number(rest[1]), properties: [] });
    else if (word === "property") {
      const property = rest[0] === "list"
        ? { name: rest[3], list: true, count: typeOf(rest[1]), item: typeOf(rest[2]) }
        : { name: rest[1], list: false, type: typeOf(rest[0]) };
      elements.at(-1).properties.push(property);
    }
  }
  const [vertex, face] = [elements.find((e) => e.name === "vertex"), elements.find((e) => e.name === "face")];
  if (!vertex || !face || elements.indexOf(vertex) > elements.indexOf(face)) {
    throw new Error("the PLY file has no vertices followed by faces: need a triangle mesh");
  }
  const view = new DataView(buffer, end);
  let at = 0;
  // Elements before the faces: fixed-size rows (this reader takes no lists there).
  let positions = new Float32Array(0);
  let colours = new Uint8Array(0);
  for (const element of elements.slice(0, elements.indexOf(face))) {
    if (element.properties.some((p) => p.list)) throw new Error(`PLY element ${element.name} has lists before the faces`);
    const offsets = {};
    let stride = 0;
    for (const p of element.properties) {
      offsets[p.name] = { offset: stride, read: p.type[0] };
      stride += p.type[1];
    }
    if (at + stride * element.count > view.byteLength) throw new Error("the PLY file is truncated");
    if (element === vertex) {
      for (const name of ["x", "y", "z"]) if (!offsets[name]) throw new Error(`the PLY vertices have no ${name}`);
      positions = new Float32Array(element.count * 3);
      colours = new Uint8Array(element.count * 3).fill(200);
      const xyz = ["x", "y", "z"].map((n) => offsets[n]);
      const rgb = ["red", "green", "blue"].map((n) => offsets[n]);
      for (let i = 0; i < element.count; i++) {
        const base = at + i * stride;
        for (let k = 0; k < 3; k++) {
          positions[3 * i + k] = view[xyz[k].read](base + xyz[k].offset, true);
          if (rgb[k]) colours[3 * i + k] = view[rgb[k].read](base + rgb[k].offset, true);
        }
      }
    }
    at += stride * element.count;
  }
  const corners = face.properties.find((p) => p.name === "vertex_indices" || p.name === "vertex_index");
  if (!corners?.list || face.properties.length !== 1) throw new Error("PLY faces must hold one vertex_indices list");
  const [readCount, countSize] = corners.count;
  const [readIndex, indexSize] = corners.item;
  const indices = [];
  const nVertices = positions.length / 3;
  for (let f = 0; f < face.count; f++) {
    if (at + countSize > view.byteLength) throw new Error("the PLY file is truncated");
    const n = view[readCount](at, true);
    at += countSize;
    if (at + n * indexSize > view.byteLength) throw new Error("the PLY file is truncated");
    const first = view[readIndex](at, true);
    for (let k = 1; k + 1 < n; k++) {
      const b = view[readIndex](at + k * indexSize, true);
      const c = view[readIndex](at + (k + 1) * indexSize, true);
      if (first >= nVertices || b >= nVertices || c >= nVertices) throw new Error(`PLY face ${f} names a vertex that does not exist`);
      indices.push(first, b, c);
    }
    at += n * indexSize;
  }
  return { positions, colours, indices: Uint32Array.from(indices) };
}
