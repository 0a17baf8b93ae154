// FPV view: the room as the drone's own camera would film it, drawn with three.js from the
// fused map's mesh (map_mesh.js) at the pose of the latest drone_state.
//
// The camera (FPV_CAMERA): mounted on the drone's nose, FPV_CAMERA.mount metres from its centre
// in the body frame (x forward, y left, z up), looking forward along body x and tilted up by
// FPV_CAMERA.uptiltDeg, as racing drones carry theirs so that the view is level in forward
// flight. It is fixed to the body: when the drone pitches, rolls or yaws, so does the picture.
// The picture is 4:3 with a horizontal field of view of FPV_CAMERA.horizontalFovDeg (a wide
// FPV lens; pinhole, no lens distortion), fitted into the view with black bars.
//
// In a shared room the other pilots' drones are in the picture too (room_pilots.js, as in the AR
// and map views; lit, in their colours), hidden by the room's mesh where it stands in between.
//
// Until the mesh arrives (the server makes it on request: seconds for a big map) the view draws
// the map's preview points (map_view.js's cloud, shared) from the same camera, and says that the
// map is loading: never an empty picture.

import * as THREE from "three";
import { matrixFromRowMajor } from "./geometry.js";
import { RENDER_BUDGET, fitRenderer } from "./render_budget.js";
import { RoomPilots } from "./room_pilots.js";

export const FPV_CAMERA = Object.freeze({
  horizontalFovDeg: 100,
  aspect: 4 / 3,
  uptiltDeg: 15,
  mount: [0.08, 0, 0.02], // body frame, metres
  nearM: 0.02,
  farM: 60,
});
const SKY = 0x27313f; // where the map has no surface (unmapped or open)
const HINTS = Object.freeze({
  none: "The drone's camera shows the mapped room once the drone has spawned and a map exists.",
  loading: "loading the map…",
});

/** T_body_camera: the GL camera (looking down -z, y up) on its mount in the body frame. */
export function bodyFromCamera({ mount, uptiltDeg } = FPV_CAMERA) {
  // GL camera axes in body coordinates: x right = -body y, y up = body z, z back = -body x.
  const level = new THREE.Matrix4().makeBasis(new THREE.Vector3(0, -1, 0), new THREE.Vector3(0, 0, 1), new THREE.Vector3(-1, 0, 0));
  const tilt = new THREE.Matrix4().makeRotationX(THREE.MathUtils.degToRad(uptiltDeg)); // about the camera's x: up
  return level.multiply(tilt).setPosition(...mount);
}

export class FPVView {
  /**
   * @param {HTMLElement} container
   * @param {{points?: THREE.BufferGeometry}} options the map's preview points (world frame,
   *   with colours), drawn until the mesh arrives; shared, never disposed here
   */
  constructor(container, { points = null } = {}) {
    this.container = container;
    // No multisampling: the mesh's colours are soft anyway, and it adds to the cost of a big
    // mesh where WebGL runs in software (headless chromium; benchmarks/page_fps.py).
    this.renderer = new THREE.WebGLRenderer({ antialias: false });
    this.renderer.setClearColor(SKY, 1);
    this.renderer.domElement.className = "fpv-canvas";
    this.hint = document.createElement("div");
    this.hint.className = "empty-hint";
    this.hint.textContent = HINTS.none;
    this.hint.setAttribute("role", "status");
    container.append(this.renderer.domElement, this.hint);
    this.scene = new THREE.Scene();
    // Colours are the camera's, already lit. Front faces only: marching cubes turns them towards
    // the free space the drone flies in, and culling the rest halves the rasterisation.
    this.material = new THREE.MeshBasicMaterial({ vertexColors: true, side: THREE.FrontSide });
    this.room = new THREE.Mesh(new THREE.BufferGeometry(), this.material);
    this.room.frustumCulled = false;
    this.room.visible = false;
    this.scene.add(this.room);
    this.points = new THREE.Points(points ?? new THREE.BufferGeometry(),
      new THREE.PointsMaterial({ size: 3, sizeAttenuation: false, vertexColors: true }));
    this.points.frustumCulled = false;
    this.points.visible = false;
    this.scene.add(this.points);
    // The other pilots' drones (world frame, as the mesh), lit as on the map (the mesh's and the
    // points' materials ignore the light: their colours are the camera's).
    this.others = new RoomPilots();
    this.others.group.visible = false;
    this.scene.add(this.others.group, new THREE.HemisphereLight(0xffffff, 0x555555, 2.2));
    const vertical = 2 * Math.atan(Math.tan(THREE.MathUtils.degToRad(FPV_CAMERA.horizontalFovDeg / 2)) / FPV_CAMERA.aspect);
    this.camera = new THREE.PerspectiveCamera(THREE.MathUtils.radToDeg(vertical), FPV_CAMERA.aspect, FPV_CAMERA.nearM, FPV_CAMERA.farM);
    this.camera.matrixAutoUpdate = false;
    this.bodyFromCamera = bodyFromCamera();
    this.droneState = null;
    this.dirty = true;
    this.lastRender = 0;
    this.lastOthers = null; // performance.now() of the last draw that turned the others' rotors
    this.budget = null; // the page's RenderBudget and PageLoad (as ARView's)
    this.meter = null;
    this.cssSize = null;
    this.buffer = {}; // fitRenderer's state
    this.lastDraw = { drawn: false, triangles: 0, points: 0, hint: HINTS.none, cameraPosition: null, others: [] };
    new ResizeObserver(() => this.layout()).observe(container);
  }

  /** The fused map's mesh (world frame) or null; shared with other views, never disposed here. */
  /** Fly with the drone of the session state (session/state.js) through the map's mesh
   * (map_mesh.js "mesh" events). */
  follow(state, { mesh }) {
    state.addEventListener("drone", ({ detail }) => this.setDroneState(detail));
    state.addEventListener("room", ({ detail: room }) => this.setRoom(room));
    mesh.addEventListener("mesh", ({ detail: geometry }) => this.setMesh(geometry));
  }

  setMesh(geometry) {
    this.room.geometry = geometry ?? new THREE.BufferGeometry();
    this.room.visible = geometry !== null;
    this.dirty = true;
  }

  setDroneState(state) {
    this.droneState = state;
    this.dirty = true;
  }

  /** The shared room's pilots (session/room.js), or null: the others' drones are drawn. Their
   * rotors turn at each draw, which the room's messages (5 a second) and the own drone's state
   * bring: no draws for the spin alone. */
  setRoom(room) {
    if (this.others.set(room)) this.dirty = true;
  }

  /** A 4:3 picture, as large as the view holds, centred. */
  layout() {
    const { clientWidth: cw, clientHeight: ch } = this.container;
    if (!cw || !ch) return;
    const scale = Math.min(cw / FPV_CAMERA.aspect, ch);
    const [w, h] = [Math.max(1, Math.round(scale * FPV_CAMERA.aspect)), Math.max(1, Math.round(scale))];
    this.cssSize = [w, h]; // the drawing buffer follows in tick (fitRenderer)
    Object.assign(this.renderer.domElement.style, { left: `${Math.round((cw - w) / 2)}px`, top: `${Math.round((ch - h) / 2)}px`,
      width: `${w}px`, height: `${h}px` });
    this.dirty = true;
  }

  /** Draw when the drone, the mesh or (without a mesh) the points changed, at most every minMs;
   * call every animation frame. */
  tick(now, minMs = this.budget?.drawIntervalMs ?? RENDER_BUDGET.drawMs) {
    const ratio = this.budget?.pixelRatio ?? Math.min(window.devicePixelRatio || 1, 2);
    if (this.cssSize && fitRenderer(this.renderer, this.buffer, ...this.cssSize, ratio, now)) this.dirty = true;
    const pointCount = this.points.geometry.drawRange.count;
    if (this.droneState && !this.room.visible && Number.isFinite(pointCount) && pointCount !== this.lastDraw.points) {
      this.dirty = true; // the map grew while the mesh is on its way
    }
    if (now - this.lastRender < minMs || !this.dirty) return;
    if (this.budget) this.budget.draw(() => this.render(now), this.meter);
    else this.render(now);
    this.lastRender = now;
  }

  render(now = performance.now()) {
    const s = this.droneState;
    const ready = s !== null && this.room.visible;
    // No mesh yet: the map's points from the drone's camera, and the word that the map loads.
    const count = this.points.geometry.drawRange.count;
    const points = s !== null && !ready && Number.isFinite(count) && count > 0 ? count : 0;
    this.points.visible = points > 0;
    const hint = ready ? "" : s !== null ? HINTS.loading : HINTS.none;
    if (this.hint.textContent !== hint && hint) this.hint.textContent = hint;
    this.hint.style.display = ready ? "none" : "";
    this.hint.classList.toggle("over-points", points > 0);
    if (s !== null) {
      this.camera.matrix.multiplyMatrices(matrixFromRowMajor(s.T_world_drone), this.bodyFromCamera);
      this.camera.matrixWorldNeedsUpdate = true;
      this.camera.updateMatrixWorld(true);
    }
    this.others.group.visible = s !== null; // from the drone's camera: none without the drone
    this.others.update(Math.min(0.1, Math.max(0, (now - (this.lastOthers ?? now)) / 1000)));
    this.lastOthers = now;
    this.renderer.render(this.scene, this.camera);
    const forward = new THREE.Vector3(0, 0, -1).transformDirection(this.camera.matrixWorld);
    this.lastDraw = { drawn: ready, triangles: ready ? this.room.geometry.index.count / 3 : 0, points, hint,
      cameraPosition: ready ? new THREE.Vector3().setFromMatrixPosition(this.camera.matrixWorld).toArray() : null,
      cameraForward: ready ? forward.toArray() : null, others: s !== null ? this.#othersDrawn() : [] };
    this.dirty = false;
  }

  /** The other pilots' drones drawn (room_pilots.js drawn()), each with where its centre is in
   * the picture: view [x, y] from 0 to 1 (x right, y down; null behind the camera or outside). */
  #othersDrawn() {
    const p = new THREE.Vector3();
    return this.others.drawn().map((drone) => {
      p.fromArray(drone.position).project(this.camera);
      const inside = p.z > -1 && p.z < 1 && Math.abs(p.x) <= 1 && Math.abs(p.y) <= 1;
      return { ...drone, view: inside ? [0.5 + 0.5 * p.x, 0.5 - 0.5 * p.y] : null };
    });
  }
}
