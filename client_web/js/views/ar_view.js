// AR view: the camera image of the latest processed frame, full size, with a three.js overlay
// whose camera has that frame's intrinsics: the drone at T_camera_drone, its ground marker, the
// planned route and the target; in a shared room, the other pilots' drones (room_pilots.js).
// Tapping the image reports the pixel in colour-image coordinates.
//
// Frames: the overlay's objects live in `root`, the three.js camera frame of the shown frame
// (CV_TO_GL * camera frame). Replay: the three camera sits at the origin with the intrinsics'
// projection. Live WebXR: root is anchored at the XR pose the frame was captured at, and the
// live source draws it over the live camera from each XR view's pose (capture/sources/live.js).

import * as THREE from "three";
import { Line2 } from "three/addons/lines/Line2.js";
import { LineGeometry } from "three/addons/lines/LineGeometry.js";
import { LineMaterial } from "three/addons/lines/LineMaterial.js";
import { createDrone, createGroundMarker, createTargetMarker } from "./drone_model.js";
import { CV_TO_GL, matrixFromRowMajor, pointsFromFlat, projectPoint, upFromGravity } from "./geometry.js";
import { Occlusion } from "./occlusion.js";
import { RoomPilots } from "./room_pilots.js";
import { projectionFromIntrinsics } from "../capture/packing.js";
import { RENDER_BUDGET, fitRenderer } from "./render_budget.js";

const TAP_MAX_MOVE_PX = 12;
const TAP_MAX_MS = 700;
const Z_AXIS = new THREE.Vector3(0, 0, 1);

export class ARView {
  /**
   * @param {HTMLElement} container
   * @param {{onTap?: (pixel: number[], seq: number, event: PointerEvent) => void}} options
   */
  constructor(container, { onTap } = {}) {
    this.container = container;
    this.onTap = onTap;
    this.stage = document.createElement("div");
    this.stage.className = "ar-stage";
    this.image = document.createElement("canvas");
    this.image.className = "ar-image";
    this.ctx = this.image.getContext("2d");
    this.renderer = new THREE.WebGLRenderer({ antialias: true, alpha: true });
    this.renderer.setClearColor(0x000000, 0);
    this.renderer.domElement.className = "ar-overlay";
    this.tapMarker = document.createElement("div");
    this.tapMarker.className = "tap-marker";
    this.lostHint = document.createElement("div");
    this.lostHint.className = "lost-hint";
    this.lostHint.textContent = "Tracking lost: point the camera at a place it has seen";
    // In a map segment (PROTOCOL.md, "Tracking recovery") poses go on but where they lie in the
    // map is a guess, and the map waits: the pilot should find a mapped place again.
    this.segmentHint = document.createElement("div");
    this.segmentHint.className = "segment-hint";
    this.segmentHint.textContent = "Placed roughly: map paused until the camera sees a mapped place";
    this.stage.append(this.image, this.renderer.domElement, this.tapMarker, this.lostHint, this.segmentHint);
    // Live AR's line for the user (move the phone, tracking lost, no depth): capture/sources/live.js.
    this.xrHint = document.createElement("div");
    this.xrHint.className = "xr-hint";
    this.xrHint.setAttribute("role", "status");
    this.xrHint.hidden = true;
    container.append(this.stage, this.xrHint);

    this.scene = new THREE.Scene();
    this.camera = new THREE.PerspectiveCamera();
    this.camera.matrixAutoUpdate = false;
    this.scene.add(new THREE.HemisphereLight(0xffffff, 0x444444, 1.6));
    const sun = new THREE.DirectionalLight(0xffffff, 1.2);
    sun.position.set(0.3, 1, 0.5);
    this.scene.add(sun);
    this.root = new THREE.Group();
    this.root.matrixAutoUpdate = false;
    this.scene.add(this.root);
    this.occlusion = new Occlusion(); // real surfaces hide the drone (occlusion.js)
    this.root.add(this.occlusion.quad, this.occlusion.mesh);
    // Objects placed in world coordinates (a course's gates): moved with the shown frame.
    this.world = new THREE.Group();
    this.world.matrixAutoUpdate = false;
    this.root.add(this.world);
    // The other pilots' drones in a shared room: world objects too, hidden by real surfaces as
    // this page's drone is (opaque, drawn after the occluder: occlusion.js). Their routes, as
    // this page's, are drawn on top (setRoom).
    this.others = new RoomPilots();
    this.world.add(this.others.group);
    for (const name of ["drone", "marker", "target"]) {
      this[name] = { drone: createDrone, marker: createGroundMarker, target: createTargetMarker }[name]();
      this[name].matrixAutoUpdate = false;
      this[name].visible = false;
      this.root.add(this[name]);
    }
    this.routeMaterial = new LineMaterial({ color: 0xffd400, linewidth: 4, transparent: true, opacity: 0.9,
      dashed: false, depthTest: false });
    this.route = new Line2(new LineGeometry(), this.routeMaterial);
    this.route.visible = false;
    this.route.renderOrder = 2;
    this.root.add(this.route);

    this.intrinsics = null;
    this.colourSize = null;
    this.frame = null; // {seq, T_world_camera, T_camera_world, bitmap}
    this.droneState = null;
    this.tracked = false; // a pose of this session was tracked (not lost) since it began
    this.up = new THREE.Vector3(0, -1, 0);
    this.groundHeight = null; // height of the floor along `up`, metres (from the map)
    this.xrAnchor = null; // live mode: (seq) => Matrix4 XR pose of that frame's GL camera
    this.lastDraw = { droneVisible: false };
    this.dirty = true; // something changed since the last draw
    this.lastRender = 0;
    this.budget = null; // the page's RenderBudget (render_budget.js): pixel ratio, draw rate
    this.meter = null; // the page's PageLoad: draws count as its "draw" work
    this.cssSize = [0, 0]; // the overlay's size on the page; its drawing buffer follows in tick
    this.buffer = {}; // fitRenderer's state
    this.#listen();
    new ResizeObserver(() => this.layout()).observe(container);
  }

  /** The colour camera: [fx, fy, cx, cy] pixels for an image of colourSize [w, h]. */
  /**
   * Draw what the session state says (session/state.js): each pose's frame with its picture,
   * the drone, and the floor height of the map; the fused mesh (map_mesh.js) for occlusion.
   * @param {{imageFor: (seq: number) => ImageBitmap|null, groundHeight: () => number|null,
   *   mesh: EventTarget}} sources the picture of a sent frame (taken, then closed here); the
   *   map's floor height, read after each map update; the map's mesh ("mesh" events)
   */
  follow(state, { imageFor, groundHeight, mesh }) {
    state.addEventListener("camera", ({ detail: { intrinsics, colourSize, gravity } }) => {
      this.setCamera(intrinsics, colourSize);
      this.setUp(upFromGravity(gravity));
    });
    state.addEventListener("pose", ({ detail: pose }) => {
      const bitmap = imageFor(pose.seq);
      this.showFrame(bitmap, pose.seq, pose.T_world_camera, pose.state, pose.recovery);
      bitmap?.close?.();
    });
    state.addEventListener("map", () => this.setGroundHeight(groundHeight()));
    state.addEventListener("drone", ({ detail }) => this.setDroneState(detail));
    state.addEventListener("reset", () => this.clearDrone());
    state.addEventListener("room", ({ detail: room }) => this.setRoom(room));
    mesh.addEventListener("mesh", ({ detail: geometry }) => {
      this.occlusion.setMesh(geometry);
      this.dirty = true;
    });
  }

  setCamera(intrinsics, colourSize) {
    this.intrinsics = [...intrinsics];
    this.colourSize = [...colourSize];
    this.image.width = colourSize[0];
    this.image.height = colourSize[1];
    this.container.style.setProperty("--ar-aspect", `${colourSize[0]} / ${colourSize[1]}`);
    this.camera.projectionMatrix.fromArray(projectionFromIntrinsics(intrinsics, ...colourSize, 0.03, 200));
    this.camera.projectionMatrixInverse.copy(this.camera.projectionMatrix).invert();
    this.layout();
  }

  setUp(up) {
    this.up.copy(up);
    this.dirty = true;
  }

  setGroundHeight(h) {
    if (h === this.groundHeight) return;
    this.groundHeight = h;
    this.dirty = true;
  }

  /** Fit the image (contain) into the container; the overlay covers exactly the image. */
  layout() {
    const { clientWidth: cw, clientHeight: ch } = this.container;
    if (!cw || !ch) return;
    const [w, h] = this.colourSize ?? [4, 3];
    const scale = Math.min(cw / w, ch / h);
    const sw = Math.max(1, Math.round(w * scale));
    const sh = Math.max(1, Math.round(h * scale));
    Object.assign(this.stage.style, {
      width: `${sw}px`, height: `${sh}px`, left: `${Math.round((cw - sw) / 2)}px`, top: `${Math.round((ch - sh) / 2)}px`,
    });
    this.cssSize = [sw, sh]; // the drawing buffer follows in tick (fitRenderer)
    this.routeMaterial.resolution.set(sw, sh);
    this.dirty = true;
  }

  /** Draw when something changed, and at most every `minMs` while the rotors spin. Cheap to
   * call every animation frame: an unchanged view is not redrawn (phones' batteries, and
   * software rendering in tests). */
  tick(now, minMs = this.budget?.drawIntervalMs ?? RENDER_BUDGET.drawMs) {
    const ratio = this.budget?.pixelRatio ?? Math.min(window.devicePixelRatio || 1, 2);
    if (fitRenderer(this.renderer, this.buffer, ...this.cssSize, ratio, now)) this.dirty = true;
    const spinning = (this.drone.visible && !["landed", "crashed"].includes(this.droneState?.mode)) ||
      (this.frame !== null && this.others.spinning);
    if (now - this.lastRender < minMs || !(this.dirty || spinning)) return;
    const dt = Math.min(0.1, (now - this.lastRender) / 1000);
    if (this.budget) this.budget.draw(() => this.render(dt), this.meter);
    else this.render(dt);
    this.lastRender = now;
  }

  /** Show a processed frame: its image (ImageBitmap or canvas source), camera pose and
   * tracking state (when lost, the pose is the last good one: the overlay is dimmed; in a map
   * segment, `recovery` "segment", the pose is a guess: a hint says so). */
  showFrame(bitmap, seq, T_world_camera, state = "ok", recovery = null) {
    this.container.classList.toggle("tracking-lost", state === "lost");
    this.container.classList.toggle("tracking-segment", recovery === "segment");
    if (bitmap) {
      this.ctx.drawImage(bitmap, 0, 0, this.image.width, this.image.height);
      this.container.classList.add("has-image");
    }
    const Twc = matrixFromRowMajor(T_world_camera);
    this.frame = { seq, T_world_camera: Twc, T_camera_world: Twc.clone().invert() };
    // A phone that joined a room has lost poses at the identity until placed: world objects
    // (the other pilots' drones) wait for its first tracked pose.
    if (state !== "lost") this.tracked = true;
    this.dirty = true;
  }

  setDroneState(state) {
    this.droneState = state;
    this.dirty = true;
  }

  clearDrone() {
    this.droneState = null;
    this.tracked = false;
    this.dirty = true;
  }

  /** The shared room's pilots (session/room.js), or null: their drones are drawn, not ours. */
  setRoom(room) {
    if (!this.others.set(room)) return;
    // The routes on top, as this page's: the occluder's depth covers only the drones' part of
    // the screen (occlusion.js), which would hide a route behind a surface only there.
    for (const line of this.others.routes.values()) {
      line.material.depthTest = false;
      line.renderOrder = 2;
    }
    this.dirty = true;
  }

  /** T_camera_drone (OpenCV camera of the shown frame) as a Matrix4, or null. */
  droneInCamera() {
    const s = this.droneState;
    if (!s || !this.frame) return null;
    if (s.T_camera_drone && (s.camera_seq === undefined || s.camera_seq === this.frame.seq)) {
      return matrixFromRowMajor(s.T_camera_drone);
    }
    // The state is for another frame's camera: go through the world frame.
    return this.frame.T_camera_world.clone().multiply(matrixFromRowMajor(s.T_world_drone));
  }

  /** Update the overlay's objects and draw. dt: seconds since the last call (rotor spin);
   * camera: the XR view's camera in live AR (capture/sources/live.js), this view's own otherwise. */
  render(dt = 0, camera = this.camera) {
    const s = this.droneState;
    const frame = this.frame;
    const Tcd = this.droneInCamera();
    if (frame && this.xrAnchor) {
      const anchor = this.xrAnchor(frame.seq);
      if (anchor) this.root.matrix.copy(anchor);
    }
    this.root.matrixWorldNeedsUpdate = true;
    this.world.visible = frame !== null;
    if (frame) this.world.matrix.multiplyMatrices(CV_TO_GL, frame.T_camera_world);
    this.drone.visible = Tcd !== null;
    this.lastDraw = { droneVisible: false };
    if (Tcd) {
      this.drone.matrix.multiplyMatrices(CV_TO_GL, Tcd);
      this.drone.userData.update(dt, s.mode !== "landed" && s.mode !== "crashed");
      const p = new THREE.Vector3().setFromMatrixPosition(Tcd);
      const pixel = projectPoint(this.intrinsics ?? [1, 1, 0, 0], [p.x, p.y, p.z]);
      this.lastDraw = { droneVisible: true, seq: frame.seq, cameraPoint: p.toArray(), pixel };
    }
    // The other pilots' drones, with the pixel each centre projects to (the tests look there).
    this.others.group.visible = this.tracked;
    this.others.update(dt);
    this.lastDraw.others = frame && this.tracked ?
      this.others.drawn({ T_camera_world: frame.T_camera_world, intrinsics: this.intrinsics }) : [];
    this.lastDraw.othersSeq = frame?.seq ?? null; // the frame those pixels are of
    if (this.dirty) {
      // Marker and route change only with the state, the frame, up or the ground: not at the
      // 30-60 Hz that rotor spin and XR frames render at (the route is a new GPU buffer).
      this.#placeGroundMarker(s, frame);
      this.#placeRoute(s, frame);
    }
    this.lastDraw.occlusion = this.occlusion.prepare(frame, this.xrAnchor !== null, this.#dronesDrawn(frame), camera);
    this.lastDraw.occlusionBoxes = this.occlusion.boxes;
    this.renderer.render(this.scene, camera);
    this.dirty = false;
  }

  /** The centres of the drones drawn now, this page's and the other pilots', in the root
   * frame: what the occluder must cover (occlusion.js). */
  #dronesDrawn(frame) {
    const centres = this.drone.visible ? [new THREE.Vector3().setFromMatrixPosition(this.drone.matrix)] : [];
    if (frame && this.others.group.visible) {
      for (const drone of this.others.drones.values()) {
        centres.push(new THREE.Vector3().setFromMatrixPosition(drone.matrix).applyMatrix4(this.world.matrix));
      }
    }
    return centres;
  }

  /** world point -> root frame (three camera of the shown frame). */
  #toRoot(frame, point) {
    return point.clone().applyMatrix4(frame.T_camera_world).applyMatrix4(CV_TO_GL);
  }

  #placeGroundMarker(s, frame) {
    this.marker.visible = false;
    this.target.visible = false;
    if (!s || !frame) return;
    const rotation = new THREE.Matrix4().extractRotation(frame.T_camera_world).premultiply(CV_TO_GL)
      .multiply(new THREE.Matrix4().makeRotationFromQuaternion(new THREE.Quaternion().setFromUnitVectors(Z_AXIS, this.up)));
    if (this.groundHeight !== null) {
      const drone = new THREE.Vector3().setFromMatrixPosition(matrixFromRowMajor(s.T_world_drone));
      const height = drone.dot(this.up) - this.groundHeight;
      const ground = drone.clone().addScaledVector(this.up, -height);
      this.marker.matrix.copy(rotation).setPosition(this.#toRoot(frame, ground));
      this.marker.userData.setHeight(height);
      this.marker.matrixWorldNeedsUpdate = true;
      this.marker.visible = true;
    }
    if (s.target) {
      this.target.matrix.copy(rotation).setPosition(this.#toRoot(frame, new THREE.Vector3(...s.target)));
      this.target.visible = true;
    }
  }

  #placeRoute(s, frame) {
    const flat = s?.route;
    if (!frame || !flat || flat.length < 6) {
      this.route.visible = false;
      return;
    }
    const positions = pointsFromFlat(flat).flatMap((p) => this.#toRoot(frame, p).toArray());
    this.route.geometry.dispose();
    this.route.geometry = new LineGeometry();
    this.route.geometry.setPositions(positions);
    this.route.computeLineDistances();
    this.route.visible = true;
  }

  /** Pixel [u, v] of the colour image under a client point, or null outside the image. */
  pixelAt(clientX, clientY) {
    if (!this.colourSize) return null;
    const rect = this.stage.getBoundingClientRect();
    const x = (clientX - rect.left) / rect.width;
    const y = (clientY - rect.top) / rect.height;
    if (x < 0 || x > 1 || y < 0 || y > 1) return null;
    // pixel centres at integers: pixel u covers [u - 0.5, u + 0.5)
    return [Math.max(0, x * this.colourSize[0] - 0.5), Math.max(0, y * this.colourSize[1] - 0.5)];
  }

  /** Client (CSS px) point of a colour-image pixel: where the tests and markers look. */
  clientPointOf([u, v]) {
    const rect = this.stage.getBoundingClientRect();
    return [rect.left + ((u + 0.5) / this.colourSize[0]) * rect.width, rect.top + ((v + 0.5) / this.colourSize[1]) * rect.height];
  }

  showTap(pixel) {
    const [x, y] = this.clientPointOf(pixel);
    const rect = this.stage.getBoundingClientRect();
    this.tapMarker.style.left = `${x - rect.left}px`;
    this.tapMarker.style.top = `${y - rect.top}px`;
    this.tapMarker.classList.remove("show");
    void this.tapMarker.offsetWidth; // restart the animation
    this.tapMarker.classList.add("show");
  }

  #listen() {
    let down = null;
    const el = this.stage;
    el.addEventListener("pointerdown", (e) => {
      down = { x: e.clientX, y: e.clientY, t: performance.now(), id: e.pointerId };
    });
    el.addEventListener("pointercancel", () => (down = null));
    el.addEventListener("pointerup", (e) => {
      if (!down || down.id !== e.pointerId) return;
      const moved = Math.hypot(e.clientX - down.x, e.clientY - down.y);
      const quick = performance.now() - down.t < TAP_MAX_MS;
      down = null;
      if (moved > TAP_MAX_MOVE_PX || !quick || !this.frame) return;
      const pixel = this.pixelAt(e.clientX, e.clientY);
      if (!pixel) return;
      this.showTap(pixel);
      this.onTap?.(pixel, this.frame.seq, e);
    });
  }
}
