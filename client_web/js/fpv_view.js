// FPV view: the room as the drone's own camera would film it, drawn with three.js from the
// fused map's mesh (map_mesh.js) at the pose of the latest drone_state.
//
// The camera (FPV_CAMERA): mounted on the drone's nose, FPV_CAMERA.mount metres from its centre
// in the body frame (x forward, y left, z up), looking forward along body x and tilted up by
// FPV_CAMERA.uptiltDeg, as racing drones carry theirs so that the view is level in forward
// flight. It is fixed to the body: when the drone pitches, rolls or yaws, so does the picture.
// The picture is 4:3 with a horizontal field of view of FPV_CAMERA.horizontalFovDeg (a wide
// FPV lens; pinhole, no lens distortion), fitted into the view with black bars.

import * as THREE from "three";
import { matrixFromRowMajor } from "./geometry.js";

export const FPV_CAMERA = Object.freeze({
  horizontalFovDeg: 100,
  aspect: 4 / 3,
  uptiltDeg: 15,
  mount: [0.08, 0, 0.02], // body frame, metres
  nearM: 0.02,
  farM: 60,
});
const SKY = 0x27313f; // where the map has no surface (unmapped or open)

/** T_body_camera: the GL camera (looking down -z, y up) on its mount in the body frame. */
export function bodyFromCamera({ mount, uptiltDeg } = FPV_CAMERA) {
  // GL camera axes in body coordinates: x right = -body y, y up = body z, z back = -body x.
  const level = new THREE.Matrix4().makeBasis(new THREE.Vector3(0, -1, 0), new THREE.Vector3(0, 0, 1), new THREE.Vector3(-1, 0, 0));
  const tilt = new THREE.Matrix4().makeRotationX(THREE.MathUtils.degToRad(uptiltDeg)); // about the camera's x: up
  return level.multiply(tilt).setPosition(...mount);
}

export class FPVView {
  /** @param {HTMLElement} container */
  constructor(container) {
    this.container = container;
    // No multisampling: the mesh's colours are soft anyway, and it adds to the cost of a big
    // mesh where WebGL runs in software (headless chromium; benchmarks/page_fps.py).
    this.renderer = new THREE.WebGLRenderer({ antialias: false });
    this.renderer.setClearColor(SKY, 1);
    this.renderer.domElement.className = "fpv-canvas";
    this.hint = document.createElement("div");
    this.hint.className = "empty-hint";
    this.hint.textContent = "The drone's camera shows the mapped room once the drone has spawned and a map exists.";
    container.append(this.renderer.domElement, this.hint);
    this.scene = new THREE.Scene();
    // Colours are the camera's, already lit. Front faces only: marching cubes turns them towards
    // the free space the drone flies in, and culling the rest halves the rasterisation.
    this.material = new THREE.MeshBasicMaterial({ vertexColors: true, side: THREE.FrontSide });
    this.room = new THREE.Mesh(new THREE.BufferGeometry(), this.material);
    this.room.frustumCulled = false;
    this.room.visible = false;
    this.scene.add(this.room);
    const vertical = 2 * Math.atan(Math.tan(THREE.MathUtils.degToRad(FPV_CAMERA.horizontalFovDeg / 2)) / FPV_CAMERA.aspect);
    this.camera = new THREE.PerspectiveCamera(THREE.MathUtils.radToDeg(vertical), FPV_CAMERA.aspect, FPV_CAMERA.nearM, FPV_CAMERA.farM);
    this.camera.matrixAutoUpdate = false;
    this.bodyFromCamera = bodyFromCamera();
    this.droneState = null;
    this.dirty = true;
    this.lastRender = 0;
    this.lastDraw = { drawn: false, triangles: 0, cameraPosition: null };
    new ResizeObserver(() => this.layout()).observe(container);
  }

  /** The fused map's mesh (world frame) or null; shared with other views, never disposed here. */
  setMesh(geometry) {
    this.room.geometry = geometry ?? new THREE.BufferGeometry();
    this.room.visible = geometry !== null;
    this.dirty = true;
  }

  setDroneState(state) {
    this.droneState = state;
    this.dirty = true;
  }

  /** A 4:3 picture, as large as the view holds, centred. */
  layout() {
    const { clientWidth: cw, clientHeight: ch } = this.container;
    if (!cw || !ch) return;
    const scale = Math.min(cw / FPV_CAMERA.aspect, ch);
    const [w, h] = [Math.max(1, Math.round(scale * FPV_CAMERA.aspect)), Math.max(1, Math.round(scale))];
    this.renderer.setPixelRatio(Math.min(window.devicePixelRatio || 1, 2));
    this.renderer.setSize(w, h);
    Object.assign(this.renderer.domElement.style, { left: `${Math.round((cw - w) / 2)}px`, top: `${Math.round((ch - h) / 2)}px` });
    this.dirty = true;
  }

  /** Draw when the drone or the mesh changed, at most every minMs; call every animation frame. */
  tick(now, minMs = 33) {
    if (now - this.lastRender < minMs || !this.dirty) return;
    this.render();
    this.lastRender = now;
  }

  render() {
    const s = this.droneState;
    const ready = s !== null && this.room.visible;
    this.hint.style.display = ready ? "none" : "";
    if (ready) {
      this.camera.matrix.multiplyMatrices(matrixFromRowMajor(s.T_world_drone), this.bodyFromCamera);
      this.camera.matrixWorldNeedsUpdate = true;
      this.camera.updateMatrixWorld(true);
    }
    this.renderer.render(this.scene, this.camera);
    const forward = new THREE.Vector3(0, 0, -1).transformDirection(this.camera.matrixWorld);
    this.lastDraw = { drawn: ready, triangles: ready ? this.room.geometry.index.count / 3 : 0,
      cameraPosition: ready ? new THREE.Vector3().setFromMatrixPosition(this.camera.matrixWorld).toArray() : null,
      cameraForward: ready ? forward.toArray() : null };
    this.dirty = false;
  }
}
