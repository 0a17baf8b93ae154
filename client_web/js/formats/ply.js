// The server's PLY downloads on the page, read with three.js's PLYLoader: the fused map's point
// cloud (GET /api/sessions/{id}/map.ply: x, y, z as double and red, green, blue as uchar per
// vertex, as Open3D writes it), so that a page reopened into a running session shows the map
// made so far (map_chunk messages only carry what is new), and the fused surface (mesh.ply:
// vertices with normals and colours, then faces) for FPV and occlusion without depth. This file
// only checks the input and hands the callers plain typed arrays.

import { ColorManagement } from "three";
import { PLYLoader } from "three/addons/loaders/PLYLoader.js";

const GREY = 200; // the colour of vertices that come without one
const HEADER_MAX_BYTES = 65536;

/**
 * Vertices of a binary PLY point cloud.
 * @param {ArrayBuffer} buffer
 * @returns {{points: Float32Array, colours: Uint8Array}} xyz (world frame, metres) and rgb per vertex
 */
export function parsePly(buffer) {
  const geometry = load(buffer);
  return { points: positionsOf(geometry), colours: coloursOf(geometry) };
}

/**
 * A triangle mesh from a binary PLY file (faces of more than three corners are split: quads
 * along their first corner, as the PLY convention says; PLYLoader reads no larger ones).
 * @param {ArrayBuffer} buffer
 * @returns {{positions: Float32Array, colours: Uint8Array, indices: Uint32Array}} xyz in metres
 *   (world frame), rgb per vertex (200 grey when the file has none), three indices per triangle
 */
export function parseMeshPly(buffer) {
  const geometry = load(buffer);
  if (!geometry.index) throw new Error("the PLY file has no faces: need a triangle mesh");
  const positions = positionsOf(geometry);
  const indices = Uint32Array.from(geometry.index.array);
  const vertices = positions.length / 3;
  for (let i = 0; i < indices.length; i++) {
    if (indices[i] >= vertices) throw new Error(`PLY face ${Math.floor(i / 3)} names a vertex that does not exist`);
  }
  return { positions, colours: coloursOf(geometry), indices };
}

/** The file's geometry, its colours as written (PLYLoader would convert sRGB bytes to linear). */
function load(buffer) {
  const head = new TextDecoder().decode(new Uint8Array(buffer, 0, Math.min(buffer.byteLength, HEADER_MAX_BYTES)));
  if (!head.startsWith("ply")) throw new Error("not a PLY file");
  if (!/\bend_header\r?\n/.test(head)) throw new Error("no PLY header");
  if (!/^format binary_(little|big)_endian 1\.0\s*$/m.test(head)) throw new Error("only binary PLY is read");
  const vertices = Number(/^element vertex (\d+)\s*$/m.exec(head)?.[1] ?? NaN);
  if (!(vertices >= 0)) throw new Error("the PLY file has no vertex element");
  const managed = ColorManagement.enabled;
  ColorManagement.enabled = false;
  try {
    const geometry = new PLYLoader().parse(buffer);
    if (geometry.getAttribute("position").count !== vertices) throw new Error("the PLY vertices have no x, y, z");
    return geometry;
  } catch (exc) {
    if (exc instanceof RangeError) throw new Error("the PLY file is truncated");
    throw exc;
  } finally {
    ColorManagement.enabled = managed;
  }
}

function positionsOf(geometry) {
  const position = geometry.getAttribute("position");
  return position.array instanceof Float32Array ? position.array : Float32Array.from(position.array);
}

/** rgb bytes per vertex: the file's uchar colours as they are, other types scaled to 0..255. */
function coloursOf(geometry) {
  const count = geometry.getAttribute("position").count;
  const colour = geometry.getAttribute("color");
  if (!colour) return new Uint8Array(3 * count).fill(GREY);
  if (colour.array instanceof Uint8Array) return colour.array;
  const scale = colour.normalized ? 255 / (2 ** (8 * colour.array.BYTES_PER_ELEMENT) - 1) : 255;
  return Uint8Array.from(colour.array, (v) => Math.round(v * scale));
}
