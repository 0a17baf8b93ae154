// Occlusion in AR: real surfaces hide the parts of the drone behind them. Before the drone is
// drawn, the AR overlay's depth buffer is filled with the depth of the real scene, and nothing
// is written to its colour: the drone's fragments behind a real surface then fail the depth test.
//
// Where the real depth comes from, best first:
// - "depth": the frame's own depth image, drawn as a full-screen quad whose fragment shader reads
//   metres from a float texture and writes the depth buffer value that the overlay camera's own
//   projection gives a point at that distance along the optical axis (so the occluder and the
//   drone share one depth scale, in replay and per XR view alike). Replay: the shown frame's
//   depth PNG, registered to its colour image (same field of view), so view and depth image
//   share normalized coordinates. Live WebXR: the current XR frame's depth buffer, looked up
//   through its normDepthBufferFromNormView (ARCore's buffer is landscape whatever the screen).
// - "mesh": the fused map (mesh.ply) drawn depth-only from the shown frame's camera pose, when
//   the frame has no depth (live, while ARCore has none yet).
// - "none": neither; the drone is drawn on top, as without occlusion.
// Both occluders are pushed back along the ray by OCCLUSION_BIAS (noise in the depth, the mesh's
// voxel size): a drone within that distance of a surface, and the ground marker lying on the
// floor, stay visible.

import * as THREE from "three";
import { CV_TO_GL } from "./geometry.js";

export const OCCLUSION_BIAS = Object.freeze({ metres: 0.04, perMetre: 0.02 }); // bias = 4 cm + 2 % of depth
const DRONE_RADIUS_M = 0.25; // centre to rotor tips, 0.23 m (drone_model.js), and a little more
const IDENTITY = new THREE.Matrix4();

// The quad covers the drone's part of the screen only (a generous box around the projection of
// its bounding sphere; all of it when the camera is about inside the sphere): depth matters only
// where the drone is drawn, and a full-screen pass that writes gl_FragDepth costs every XR frame.
const QUAD_VERTEX = /* glsl */ `
  uniform vec3 droneCentre;  // in the quad's frame (the overlay's root, as the drone)
  uniform float droneRadius; // metres
  varying vec2 vView;        // normalized view coordinates: x right, y down, origin top left
  varying vec4 vDepthTerms;  // projection entries that map eye-space z to clip z and w
  void main() {
    vec4 c = projectionMatrix * modelViewMatrix * vec4(droneCentre, 1.0);
    vec2 centre = vec2(0.0);
    vec2 halfSize = vec2(1.0);
    if (c.w > 2.0 * droneRadius) {
      centre = c.xy / c.w;
      halfSize = 2.0 * droneRadius * vec2(abs(projectionMatrix[0][0]), abs(projectionMatrix[1][1])) / (c.w - droneRadius);
    } else if (c.w < -2.0 * droneRadius) {
      halfSize = vec2(0.0); // behind the camera: nothing of the drone is drawn
    }
    vec2 ndc = clamp(centre + position.xy * halfSize, -1.0, 1.0);
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

export class Occlusion {
  constructor() {
    this.enabled = true;
    this.depth = null; // {seq (null: the current XR frame), texture, width, height}
    this.source = "none"; // what hid the drone in the last draw: depth, mesh or none
    const bias = new THREE.Vector2(OCCLUSION_BIAS.metres, OCCLUSION_BIAS.perMetre);
    this.quadMaterial = new THREE.ShaderMaterial({
      uniforms: { depthMetres: { value: null }, depthFromView: { value: new THREE.Matrix4() }, bias: { value: bias },
        droneCentre: { value: new THREE.Vector3() }, droneRadius: { value: DRONE_RADIUS_M } },
      vertexShader: QUAD_VERTEX, fragmentShader: QUAD_FRAGMENT,
      colorWrite: false, depthWrite: true, depthTest: true, depthFunc: THREE.AlwaysDepth,
    });
    /** Add to the overlay's root (the shown frame's GL camera frame), like the drone. */
    this.quad = new THREE.Mesh(new THREE.PlaneGeometry(2, 2), this.quadMaterial);
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
   * @param {THREE.Matrix4|null} drone the drone's pose in the root frame, or null when not drawn
   */
  prepare(frame, live = false, drone = null) {
    const depthFits = this.depth !== null && (live ? this.depth.seq === null : this.depth.seq === frame?.seq);
    this.source = !this.enabled || !frame ? "none" : depthFits ? "depth" : this.hasMesh ? "mesh" : "none";
    // Nothing to hide without the drone: the ground marker and target lie on surfaces anyway.
    this.quad.visible = this.source === "depth" && drone !== null;
    this.mesh.visible = this.source === "mesh" && drone !== null;
    if (drone) this.quadMaterial.uniforms.droneCentre.value.setFromMatrixPosition(drone);
    if (this.mesh.visible) {
      this.mesh.matrix.multiplyMatrices(CV_TO_GL, frame.T_camera_world);
      this.mesh.matrixWorldNeedsUpdate = true;
    }
    return this.source;
  }
}
