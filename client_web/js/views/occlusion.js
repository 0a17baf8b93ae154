// Occlusion in AR: real surfaces hide the parts of the drones behind them (this page's drone
// and, in a shared room, the other pilots': room_pilots.js). Before the drones are drawn, the AR
// overlay's depth buffer is filled with the depth of the real scene, and nothing is written to
// its colour: the drones' fragments behind a real surface then fail the depth test.
//
// Where the real depth comes from, best first:
// - "depth": the frame's own depth image, drawn as a full-screen quad whose fragment shader reads
//   metres from a float texture and writes the depth buffer value that the overlay camera's own
//   projection gives a point at that distance along the optical axis (so the occluder and the
//   drones share one depth scale, in replay and per XR view alike). Replay: the shown frame's
//   depth PNG, registered to its colour image (same field of view), so view and depth image
//   share normalized coordinates. Live WebXR: the current XR frame's depth buffer, looked up
//   through its normDepthBufferFromNormView (ARCore's buffer is landscape whatever the screen).
// - "mesh": the fused map (mesh.ply) drawn depth-only from the shown frame's camera pose, when
//   the frame has no depth (live, while ARCore has none yet).
// - "none": neither; the drones are drawn on top, as without occlusion.
// Both occluders are pushed back along the ray by OCCLUSION_BIAS (noise in the depth, the mesh's
// voxel size): a drone within that distance of a surface, and the ground marker lying on the
// floor, stay visible. Both are drawn first (renderOrder below everything else), and only while
// a drone is drawn.

import * as THREE from "three";
import { CV_TO_GL } from "./geometry.js";

export const OCCLUSION_BIAS = Object.freeze({ metres: 0.04, perMetre: 0.02 }); // bias = 4 cm + 2 % of depth
const DRONE_RADIUS_M = 0.25; // centre to rotor tips, 0.23 m (drone_model.js), and a little more
const IDENTITY = new THREE.Matrix4();

// The quad covers the drones' part of the screen only: depth matters only where a drone is drawn,
// and a full-screen pass that writes gl_FragDepth costs every XR frame. Each drone has a box (a
// generous one around the projection of its bounding sphere: droneBox; all of the screen when the
// camera is about inside the sphere), and boxes are merged into the box around them where that
// box has no more pixels than they have together (mergeBoxes): drones apart on the screen keep a
// box each (one box around them all would cover most of the screen between them), drones close
// together share one (their boxes would be drawn over each other). All boxes in one draw call.
// Measured in headless chromium (software WebGL, 1080 x 810 pixels, 4 drones 3 m away; what the
// quad adds to a draw): apart on the screen, a box each +10 ms, the box around all +19 ms; close
// together, +5 ms and +3 ms; merged as here, +10 ms and +3 ms. The boxes are worked out here
// per draw for the camera that draws (each XR view's own pose and projection).
const QUAD_VERTEX = /* glsl */ `
  attribute vec4 box;       // x0, y0, x1, y1 in normalized device coordinates
  varying vec2 vView;       // normalized view coordinates: x right, y down, origin top left
  varying vec4 vDepthTerms; // projection entries that map eye-space z to clip z and w
  void main() {
    vec2 ndc = mix(box.xy, box.zw, 0.5 + 0.5 * position.xy);
    vView = vec2(0.5 + 0.5 * ndc.x, 0.5 - 0.5 * ndc.y);
    vDepthTerms = vec4(projectionMatrix[2][2], projectionMatrix[3][2], projectionMatrix[2][3], projectionMatrix[3][3]);
    gl_Position = vec4(ndc, 0.0, 1.0);
  }`;

const QUAD_FRAGMENT = /* glsl */ `
  uniform sampler2D depthMetres;
  uniform mat4 depthFromView; // normalized view -> normalized depth-image coordinates
  uniform vec2 bias;          // metres, per metre
  varying vec2 vView;
  varying vec4 vDepthTerms;
  void main() {
    vec4 p = depthFromView * vec4(vView, 0.0, 1.0);
    vec2 uv = p.xy / p.w;
    if (uv.x < 0.0 || uv.y < 0.0 || uv.x >= 1.0 || uv.y >= 1.0) discard;
    float d = texture2D(depthMetres, uv).r; // holes filled on upload (fillDepthHoles)
    if (!(d > 0.0)) discard; // no measurement near: nothing hides the drone here
    d += bias.x + bias.y * d;
    float z = vDepthTerms.x * -d + vDepthTerms.y;
    float w = vDepthTerms.z * -d + vDepthTerms.w;
    gl_FragDepth = clamp(0.5 * z / w + 0.5, 0.0, 1.0);
    gl_FragColor = vec4(0.0);
  }`;

// The mesh, drawn where it is but each vertex pushed away from the camera by the bias: the same
// pixels, a slightly larger depth.
const MESH_VERTEX = /* glsl */ `
  uniform vec2 bias;
  void main() {
    vec4 eye = modelViewMatrix * vec4(position, 1.0);
    float d = max(1e-4, -eye.z);
    eye.xyz *= (d + bias.x + bias.y * d) / d;
    gl_Position = projectionMatrix * eye;
  }`;

const MESH_FRAGMENT = /* glsl */ `void main() { gl_FragColor = vec4(0.0); }`;

/**
 * Depth with its holes filled: each sample without a measurement (0) takes the nearest valid
 * depth within `radius` pixels (the square around it), else stays 0. Depth sensors leave holes
 * at grazing angles and on dark or shiny surfaces, which would let the drone show through a
 * surface in specks; the nearest depth errs on the side of hiding, by at most `radius` depth
 * pixels beside an edge. Done once per depth image, not per drawn pixel.
 * @param {ArrayLike<number>} depth width x height, row-major, in units of `scale` metres
 *   (1: metres; a phone's raw depth with its rawValueToMeters, read as it is)
 * @param {Float32Array} out the same size (may not be `depth`), metres
 */
export function fillDepthHoles(depth, width, height, out, radius = 2, scale = 1) {
  for (let y = 0; y < height; y++) {
    for (let x = 0; x < width; x++) {
      const i = y * width + x;
      let d = depth[i];
      if (!(d > 0)) {
        d = Infinity;
        for (let v = Math.max(0, y - radius); v <= Math.min(height - 1, y + radius); v++) {
          for (let u = Math.max(0, x - radius); u <= Math.min(width - 1, x + radius); u++) {
            const s = depth[v * width + u];
            if (s > 0 && s < d) d = s;
          }
        }
        if (d === Infinity) d = 0;
      }
      out[i] = d * scale;
    }
  }
  return out;
}

/**
 * The screen box that holds a drone drawn by a camera: [x0, y0, x1, y1] in normalized device
 * coordinates (-1 to 1), or null when none of it is in front of the camera.
 * @param {THREE.Vector4} clip the drone's centre in clip coordinates (projection * view * point)
 * @param {THREE.Matrix4} projection the camera's projection
 */
export function droneBox(clip, projection, radius = DRONE_RADIUS_M) {
  const e = projection.elements;
  let box = [-1, -1, 1, 1]; // the camera about inside the drone's sphere: all of the screen
  if (clip.w > 2 * radius) {
    const [x, y] = [clip.x / clip.w, clip.y / clip.w];
    const [hx, hy] = [2 * radius * Math.abs(e[0]) / (clip.w - radius), 2 * radius * Math.abs(e[5]) / (clip.w - radius)];
    box = [x - hx, y - hy, x + hx, y + hy].map((v) => Math.min(1, Math.max(-1, v)));
  } else if (clip.w < -2 * radius) {
    return null; // behind the camera: nothing of the drone is drawn
  }
  return box[2] > box[0] && box[3] > box[1] ? box : null;
}

const area = (b) => (b[2] - b[0]) * (b[3] - b[1]);
const around = (a, b) => [Math.min(a[0], b[0]), Math.min(a[1], b[1]), Math.max(a[2], b[2]), Math.max(a[3], b[3])];

/** Boxes merged, two at a time, into the box around them wherever that box has no more pixels
 * than the two together (pixels where they overlap count twice: drawn twice). -> new boxes. */
export function mergeBoxes(boxes) {
  const out = boxes.map((b) => [...b]);
  for (let merged = true; merged;) {
    merged = false;
    for (let i = 0; i < out.length && !merged; i++) {
      for (let j = i + 1; j < out.length && !merged; j++) {
        const both = around(out[i], out[j]);
        if (area(both) <= area(out[i]) + area(out[j])) {
          out[i] = both;
          out.splice(j, 1);
          merged = true;
        }
      }
    }
  }
  return out;
}

/** Corners of a box, in units of its half size from its centre: two triangles. */
const CORNERS = [[-1, -1], [1, -1], [1, 1], [-1, 1]];
const CORNER_TRIANGLES = [0, 1, 2, 0, 2, 3];

/** Room for `capacity` boxes: their corners, each corner's box (set per draw), the triangles. */
function boxesGeometry(capacity) {
  const corners = new Float32Array(capacity * 12);
  const index = [];
  for (let b = 0; b < capacity; b++) {
    CORNERS.forEach(([x, y], i) => corners.set([x, y, 0], 12 * b + 3 * i));
    index.push(...CORNER_TRIANGLES.map((i) => 4 * b + i));
  }
  const geometry = new THREE.BufferGeometry();
  geometry.setAttribute("position", new THREE.BufferAttribute(corners, 3));
  const boxes = new THREE.BufferAttribute(new Float32Array(capacity * 16), 4);
  boxes.setUsage(THREE.DynamicDrawUsage);
  geometry.setAttribute("box", boxes);
  geometry.setIndex(index);
  geometry.setDrawRange(0, 0);
  return geometry;
}

const CLIP = new THREE.Vector4();
const MODEL_VIEW_PROJECTION = new THREE.Matrix4();

export class Occlusion {
  constructor() {
    this.enabled = true;
    this.depth = null; // {seq (null: the current XR frame), texture, width, height}
    this.source = "none"; // what hid the drones in the last draw: depth, mesh or none
    this.boxes = 0; // the depth quad's boxes in the last draw (a drone's, or drones' merged)
    const bias = new THREE.Vector2(OCCLUSION_BIAS.metres, OCCLUSION_BIAS.perMetre);
    this.quadMaterial = new THREE.ShaderMaterial({
      uniforms: { depthMetres: { value: null }, depthFromView: { value: new THREE.Matrix4() }, bias: { value: bias } },
      vertexShader: QUAD_VERTEX, fragmentShader: QUAD_FRAGMENT,
      colorWrite: false, depthWrite: true, depthTest: true, depthFunc: THREE.AlwaysDepth,
    });
    /** Add to the overlay's root (the shown frame's GL camera frame), like the drone. */
    this.quad = new THREE.Mesh(boxesGeometry(4), this.quadMaterial);
    this.quad.frustumCulled = false;
    this.quad.renderOrder = -100; // before everything else that is opaque
    this.quad.visible = false;
    /** Add to the overlay's root (the shown frame's GL camera frame), like the drone. */
    this.mesh = new THREE.Mesh(new THREE.BufferGeometry(), new THREE.ShaderMaterial({
      uniforms: { bias: { value: bias } }, vertexShader: MESH_VERTEX, fragmentShader: MESH_FRAGMENT,
      colorWrite: false, side: THREE.DoubleSide,
    }));
    this.mesh.matrixAutoUpdate = false;
    this.mesh.frustumCulled = false;
    this.mesh.renderOrder = -101;
    this.mesh.visible = false;
    this.hasMesh = false;
    this.depthMissingSince = null; // performance.now() since which live AR has had no depth
  }

  /**
   * Real depth for the overlay, along the optical axis (0: no measurement).
   * @param {ArrayLike<number>} depth row-major, width x height, top row first, in units of
   *   `scale` metres (a phone's raw depth buffer with its rawValueToMeters, not copied first)
   * @param {number|null} seq the frame it belongs to (replay), or null for "the current XR frame"
   * @param {Float32Array|number[]|null} depthFromView 4x4 column-major (WebXR's
   *   normDepthBufferFromNormView.matrix); null: the depth image has the view's field of view
   */
  setDepth(depth, width, height, seq = null, depthFromView = null, scale = 1) {
    let texture = this.depth?.texture;
    if (!texture || this.depth.width !== width || this.depth.height !== height) {
      texture?.dispose();
      texture = new THREE.DataTexture(new Float32Array(width * height), width, height, THREE.RedFormat, THREE.FloatType);
      texture.minFilter = texture.magFilter = THREE.NearestFilter; // never blend a near edge with the far side
    }
    fillDepthHoles(depth, width, height, texture.image.data, 2, scale);
    texture.needsUpdate = true;
    this.depth = { seq, texture, width, height };
    this.depthMissingSince = null;
    this.quadMaterial.uniforms.depthMetres.value = texture;
    if (depthFromView) this.quadMaterial.uniforms.depthFromView.value.fromArray(depthFromView);
    else this.quadMaterial.uniforms.depthFromView.value.copy(IDENTITY);
  }

  /** This XR frame has no depth: the mesh (or nothing) hides the drone until it does. */
  clearDepth() {
    this.depth = null;
    this.depthMissingSince ??= performance.now();
  }

  /** The fused map's mesh (world frame), or null. Shared with other views; never disposed here. */
  setMesh(geometry) {
    this.hasMesh = geometry !== null;
    this.mesh.geometry = geometry ?? new THREE.BufferGeometry();
  }

  /**
   * Choose the occluder for the next draw.
   * @param {{seq: number, T_camera_world: THREE.Matrix4}|null} frame the shown frame
   * @param {boolean} live the overlay is drawn over the live XR camera (depth of the current frame)
   * @param {THREE.Vector3[]} drones the centres of the drones drawn (this page's and the other
   *   pilots'), in the root frame (the quad's parent); none: nothing to hide
   * @param {THREE.Camera|null} camera the camera that draws (its pose and projection place the
   *   depth quad's boxes)
   */
  prepare(frame, live = false, drones = [], camera = null) {
    const depthFits = this.depth !== null && (live ? this.depth.seq === null : this.depth.seq === frame?.seq);
    this.source = !this.enabled || !frame ? "none" : depthFits ? "depth" : this.hasMesh ? "mesh" : "none";
    // Nothing to hide without a drone: the ground marker and target lie on surfaces anyway.
    const boxes = this.source === "depth" && camera ? this.#boxes(drones, camera) : [];
    this.quad.visible = boxes.length > 0;
    this.mesh.visible = this.source === "mesh" && drones.length > 0;
    this.boxes = boxes.length;
    if (this.quad.visible) this.#placeBoxes(boxes);
    if (this.mesh.visible) {
      this.mesh.matrix.multiplyMatrices(CV_TO_GL, frame.T_camera_world);
      this.mesh.matrixWorldNeedsUpdate = true;
    }
    return this.source;
  }

  /** The drones' screen boxes for this camera, merged where that draws fewer pixels. */
  #boxes(drones, camera) {
    if (drones.length === 0) return [];
    camera.updateMatrixWorld();
    this.quad.updateWorldMatrix(true, false);
    MODEL_VIEW_PROJECTION.multiplyMatrices(camera.projectionMatrix, camera.matrixWorldInverse)
      .multiply(this.quad.matrixWorld);
    const boxes = [];
    for (const c of drones) {
      const box = droneBox(CLIP.set(c.x, c.y, c.z, 1).applyMatrix4(MODEL_VIEW_PROJECTION), camera.projectionMatrix);
      if (box) boxes.push(box);
    }
    return mergeBoxes(boxes);
  }

  /** The quad's boxes: each box's four corners carry it. */
  #placeBoxes(boxes) {
    let geometry = this.quad.geometry;
    let attribute = geometry.getAttribute("box");
    if (attribute.count < 4 * boxes.length) { // more boxes than room: room for twice as many
      geometry.dispose();
      geometry = this.quad.geometry = boxesGeometry(2 * boxes.length);
      attribute = geometry.getAttribute("box");
    }
    boxes.forEach((box, b) => {
      for (let i = 0; i < 4; i++) attribute.setXYZW(4 * b + i, ...box);
    });
    attribute.needsUpdate = true;
    geometry.setDrawRange(0, CORNER_TRIANGLES.length * boxes.length);
  }
}
