// Map view: the fused map preview (map_chunk points) as a point cloud coloured by height (a heat
// map, or the points' own colours), the camera trajectory and current camera, the drone with its
// route and target, and in a shared room the other pilots' drones and cameras (room_pilots.js);
// orbit, pan and zoom by touch or mouse; a tap picks a 3D point of the cloud.

import * as THREE from "three";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";
import { DRONE_COLOUR, createDrone, createTargetMarker } from "./drone_model.js";
import { matrixFromRowMajor, pointsFromFlat, turbo, upFromGravity } from "./geometry.js";
import { fitRenderer } from "./render_budget.js";
import { RoomPilots } from "./room_pilots.js";

const TAP_MAX_MOVE_PX = 10;
const TAP_MAX_MS = 600;
const STANDOFF_M = 0.35; // a picked surface point is moved this far towards the viewer

/** A growable float/byte buffer attribute. */
class Growable {
  constructor(itemSize, ArrayType, capacity = 1 << 16) {
    this.itemSize = itemSize;
    this.ArrayType = ArrayType;
    this.count = 0;
    this.array = new ArrayType(capacity * itemSize);
  }

  append(values) {
    const n = values.length / this.itemSize;
    if ((this.count + n) * this.itemSize > this.array.length) {
      let capacity = this.array.length / this.itemSize;
      while (capacity < this.count + n) capacity *= 2;
      const bigger = new this.ArrayType(capacity * this.itemSize);
      bigger.set(this.array.subarray(0, this.count * this.itemSize));
      this.array = bigger;
    }
    this.array.set(values, this.count * this.itemSize);
    this.count += n;
  }
}

export class MapView {
  /** @param {HTMLElement} container @param {{onPick?: (point: number[], event) => void}} options */
  constructor(container, { onPick } = {}) {
    this.container = container;
    this.onPick = onPick;
    this.renderer = new THREE.WebGLRenderer({ antialias: true });
    this.renderer.setClearColor(0x11151c, 1);
    this.renderer.domElement.className = "map-canvas";
    container.append(this.renderer.domElement);
    this.scene = new THREE.Scene();
    this.camera = new THREE.PerspectiveCamera(55, 1, 0.02, 500);
    this.scene.add(new THREE.HemisphereLight(0xffffff, 0x555555, 2.2));
    this.up = new THREE.Vector3(0, -1, 0);

    this.positions = new Growable(3, Float32Array);
    this.rgb = new Growable(3, Uint8Array);
    this.heights = new Growable(1, Float32Array);
    this.colourMode = "height"; // or "rgb"
    this.range = null; // [low, high] heights of the colour scale
    this.geometry = new THREE.BufferGeometry();
    this.material = new THREE.PointsMaterial({ size: 3, sizeAttenuation: false, vertexColors: true });
    this.points = new THREE.Points(this.geometry, this.material);
    this.points.frustumCulled = false;
    this.scene.add(this.points);
    this.#rebuildAttributes();

    this.trajectory = new Growable(3, Float32Array, 4096);
    this.trajectoryLine = new THREE.Line(new THREE.BufferGeometry(), new THREE.LineBasicMaterial({ color: 0x4fc3f7 }));
    this.trajectoryLine.frustumCulled = false;
    this.scene.add(this.trajectoryLine);
    this.cameraMarker = this.#cameraFrustum();
    this.scene.add(this.cameraMarker);

    this.drone = createDrone();
    this.drone.matrixAutoUpdate = false;
    this.drone.scale.setScalar(1);
    this.drone.visible = false;
    this.scene.add(this.drone);
    // The halo is the drone's collision sphere (the simulation's radius_m, 0.12 m by default).
    this.droneHalo = new THREE.Mesh(new THREE.SphereGeometry(0.12, 20, 14),
      new THREE.MeshBasicMaterial({ color: DRONE_COLOUR, transparent: true, opacity: 0.18, depthWrite: false }));
    this.droneHalo.visible = false;
    this.scene.add(this.droneHalo);
    this.target = createTargetMarker();
    this.target.visible = false;
    this.scene.add(this.target);
    this.route = new THREE.Line(new THREE.BufferGeometry(), new THREE.LineBasicMaterial({ color: 0xffd400 }));
    this.route.frustumCulled = false;
    this.route.visible = false;
    this.scene.add(this.route);
    this.others = new RoomPilots({ cameras: true, halo: true }); // the room's other phones
    this.scene.add(this.others.group);

    this.#makeControls();
    this.dirty = true;
    this.lastRender = 0;
    this.budget = null; // the page's RenderBudget and PageLoad (as ARView's)
    this.meter = null;
    this.buffer = {}; // fitRenderer's state
    this.raycaster = new THREE.Raycaster();
    this.#listen();
    new ResizeObserver(() => this.layout()).observe(container);
    this.layout();
  }

  /** Draw what the session state says (session/state.js): the camera's poses and trail, the
   * map's points, loop corrections and the drone; a new session clears it all. */
  follow(state) {
    state.addEventListener("camera", ({ detail: { gravity } }) => this.setUp(upFromGravity(gravity)));
    state.addEventListener("pose", ({ detail: pose }) => this.addCameraPose(pose.T_world_camera));
    state.addEventListener("map", ({ detail: { points, colours, reset } }) => this.addPoints(points, colours, reset));
    state.addEventListener("trail", ({ detail: { positions } }) => positions.forEach((p) => this.addTrajectoryPoint(p)));
    // The trail through the corrected keyframes: the poses before the correction are not resent.
    state.addEventListener("corrected", ({ detail }) => this.replaceTrajectory(detail.keyframes.map((k) => k.T_world_keyframe)));
    state.addEventListener("drone", ({ detail }) => this.setDroneState(detail));
    state.addEventListener("reset", () => {
      this.clear();
      this.setDroneState(null);
    });
    state.addEventListener("room", ({ detail: room }) => this.setRoom(room));
  }

  get pointCount() {
    return this.positions.count;
  }

  /** World up (against gravity); re-aims the orbit controls around it. */
  setUp(up) {
    this.up.copy(up);
    this.camera.up.copy(up);
    this.#makeControls();
    this.#recolour();
  }

  #makeControls() {
    this.controls?.dispose();
    this.controls = new OrbitControls(this.camera, this.renderer.domElement);
    this.controls.enableDamping = true;
    this.controls.screenSpacePanning = true;
    this.controls.addEventListener("change", () => (this.dirty = true));
    this.fitted = false;
  }

  layout() {
    const { clientWidth: w, clientHeight: h } = this.container;
    if (!w || !h) return;
    this.cssSize = [w, h]; // the canvas fills the view (CSS); its drawing buffer follows in tick
    this.camera.aspect = w / h;
    this.camera.updateProjectionMatrix();
    this.dirty = true;
  }

  clear() {
    this.clearPoints();
    this.fitted = false;
    this.trajectory.count = 0;
    this.trajectoryLine.geometry.setDrawRange(0, 0);
  }

  /** Drop the map's points (a rebuilt map is resent); the trajectory stays. */
  clearPoints() {
    for (const g of [this.positions, this.rgb, this.heights]) g.count = 0;
    this.range = null;
    this.#rebuildAttributes();
    this.dirty = true;
  }

  /** Add map_chunk points (Float32Array xyz, world frame, metres) with colours (Uint8Array rgb);
   * reset: they replace the points so far (the server rebuilt its map). */
  addPoints(points, colours, reset = false) {
    if (reset) this.clearPoints();
    const n = points.length / 3;
    const heights = new Float32Array(n);
    for (let i = 0; i < n; i++) {
      heights[i] = points[3 * i] * this.up.x + points[3 * i + 1] * this.up.y + points[3 * i + 2] * this.up.z;
    }
    const capacity = this.positions.array.length;
    this.positions.append(points);
    this.rgb.append(colours);
    this.heights.append(heights);
    const range = this.#robustRange();
    const grown = !this.range || range[0] < this.range[0] - 0.05 || range[1] > this.range[1] + 0.05;
    if (capacity !== this.positions.array.length || grown) {
      if (grown) this.range = range;
      this.#rebuildAttributes();
    } else {
      this.#colourRange(this.positions.count - n, this.positions.count);
      this.#upload(this.positions.count - n);
    }
    if (!this.fitted && this.positions.count > 500) this.fit();
    this.dirty = true;
  }

  /** Height of the floor along `up`: a low percentile of the map's heights, or null. */
  groundHeight() {
    if (this.heights.count < 200) return null;
    return this.#percentiles([0.02])[0];
  }

  setColourMode(mode) {
    this.colourMode = mode;
    this.#recolour();
  }

  addCameraPose(T_world_camera) {
    const m = matrixFromRowMajor(T_world_camera);
    const p = new THREE.Vector3().setFromMatrixPosition(m);
    this.addTrajectoryPoint(p.toArray());
    this.cameraMarker.matrix.copy(m);
    this.cameraMarker.visible = true;
  }

  /** Redraw the trajectory through these poses (T_world_camera, 16 numbers row-major each): the
   * corrected keyframes after a loop closure; later poses extend it. */
  replaceTrajectory(poses) {
    this.trajectory.count = 0;
    for (const T of poses) this.trajectory.append([T[3], T[7], T[11]]);
    const g = this.trajectoryLine.geometry;
    g.setAttribute("position", new THREE.BufferAttribute(this.trajectory.array, 3));
    g.setDrawRange(0, this.trajectory.count);
    g.boundingSphere = null;
    this.dirty = true;
  }

  /** Extend the camera trajectory by a position [x, y, z], world frame, metres. */
  addTrajectoryPoint(p) {
    this.trajectory.append(p);
    const g = this.trajectoryLine.geometry;
    if (g.getAttribute("position")?.array !== this.trajectory.array) {
      g.setAttribute("position", new THREE.BufferAttribute(this.trajectory.array, 3));
    }
    g.getAttribute("position").needsUpdate = true;
    g.setDrawRange(0, this.trajectory.count);
    g.boundingSphere = null;
    this.dirty = true;
  }

  setDroneState(s) {
    this.dirty = true;
    if (!s) {
      this.drone.visible = this.droneHalo.visible = this.route.visible = this.target.visible = false;
      return;
    }
    this.drone.matrix.copy(matrixFromRowMajor(s.T_world_drone));
    this.drone.matrixWorldNeedsUpdate = true;
    this.drone.visible = true;
    this.droneHalo.position.setFromMatrixPosition(this.drone.matrix);
    this.droneHalo.visible = true;
    this.drone.userData.spinning = s.mode !== "landed" && s.mode !== "crashed";
    if (s.route && s.route.length >= 6) {
      this.route.geometry.dispose();
      this.route.geometry = new THREE.BufferGeometry().setFromPoints(pointsFromFlat(s.route));
      this.route.visible = true;
    } else {
      this.route.visible = false;
    }
    if (s.target) {
      this.target.position.set(...s.target);
      this.target.quaternion.setFromUnitVectors(new THREE.Vector3(0, 0, 1), this.up);
      this.target.visible = true;
    } else {
      this.target.visible = false;
    }
  }

  /** The shared room's pilots (session/room.js), or null: the others' drones and cameras. */
  setRoom(room) {
    if (this.others.set(room)) this.dirty = true;
  }

  /** Frame the map (or the trajectory) from above and behind. */
  fit() {
    const box = new THREE.Box3();
    const src = this.positions.count ? this.positions : this.trajectory;
    if (!src.count) return;
    const step = Math.max(1, Math.floor(src.count / 5000));
    const p = new THREE.Vector3();
    for (let i = 0; i < src.count; i += step) box.expandByPoint(p.fromArray(src.array, 3 * i));
    const centre = box.getCenter(new THREE.Vector3());
    const radius = Math.max(0.5, box.getSize(new THREE.Vector3()).length() / 2);
    // Look from above at 55 degrees, along the first camera's forward (world +z) projected.
    const forward = new THREE.Vector3(0, 0, 1).addScaledVector(this.up, -this.up.z).normalize();
    const eye = centre.clone().addScaledVector(forward, -radius * 1.1).addScaledVector(this.up, radius * 1.5);
    this.camera.position.copy(eye);
    this.controls.target.copy(centre);
    this.controls.update();
    this.fitted = true;
    this.dirty = true;
  }

  /** Draw when something changed (new points, poses, drone state, the user orbiting), at most
   * every `minMs` for data updates; call it every animation frame. */
  tick(now, minMs = Math.max(50, this.budget?.drawIntervalMs ?? 0)) {
    this.controls.update(); // damping: fires "change" while the view still moves
    const ratio = this.budget?.pixelRatio ?? Math.min(window.devicePixelRatio || 1, 2);
    if (this.cssSize && fitRenderer(this.renderer, this.buffer, ...this.cssSize, ratio, now)) this.dirty = true;
    const spinning = (this.drone.visible && this.drone.userData.spinning) || this.others.spinning;
    if (now - this.lastRender < minMs || !(this.dirty || spinning)) return;
    const dt = Math.min(0.1, (now - this.lastRender) / 1000);
    this.drone.userData.update(dt, this.drone.visible && this.drone.userData.spinning);
    this.others.update(dt);
    const draw = () => this.renderer.render(this.scene, this.camera);
    if (this.budget) this.budget.draw(draw, this.meter);
    else draw();
    this.lastRender = now;
    this.dirty = false;
  }

  /** The map point under a client point (the nearest cloud point near the ray), or null. */
  pick(clientX, clientY) {
    if (!this.positions.count) return null;
    const rect = this.renderer.domElement.getBoundingClientRect();
    const ndc = new THREE.Vector2(((clientX - rect.left) / rect.width) * 2 - 1, -((clientY - rect.top) / rect.height) * 2 + 1);
    this.raycaster.setFromCamera(ndc, this.camera);
    const distance = this.camera.position.distanceTo(this.controls.target);
    this.raycaster.params.Points.threshold = Math.max(0.02, distance * 0.012);
    const hits = this.raycaster.intersectObject(this.points);
    if (!hits.length) return null;
    const hit = hits[0]; // the nearest to the viewer: the surface seen there
    return { surface: hit.point.toArray(), ray: this.raycaster.ray.direction.toArray() };
  }

  /** A fly-to target for a picked surface point: standoff metres back along the view ray. */
  static targetFor({ surface, ray }, standoff = STANDOFF_M) {
    return surface.map((v, i) => v - ray[i] * standoff);
  }

  // ---- internals ------------------------------------------------------------------------------

  #cameraFrustum() {
    // A small pyramid in the OpenCV camera frame (apex at the centre, z forward, y down).
    const c = [0, 0, 0];
    const corners = [[-0.12, -0.09, 0.15], [0.12, -0.09, 0.15], [0.12, 0.09, 0.15], [-0.12, 0.09, 0.15]];
    const segments = [];
    corners.forEach((q, i) => segments.push(c, q, q, corners[(i + 1) % 4]));
    segments.push([-0.04, -0.09, 0.15], [0, -0.14, 0.15], [0, -0.14, 0.15], [0.04, -0.09, 0.15]); // "up" tick
    const g = new THREE.BufferGeometry().setFromPoints(segments.map((v) => new THREE.Vector3(...v)));
    const marker = new THREE.LineSegments(g, new THREE.LineBasicMaterial({ color: 0xffffff }));
    marker.matrixAutoUpdate = false;
    marker.visible = false;
    return marker;
  }

  #percentiles(qs) {
    const n = this.heights.count;
    const step = Math.max(1, Math.floor(n / 4000));
    const sample = [];
    for (let i = 0; i < n; i += step) sample.push(this.heights.array[i]);
    sample.sort((a, b) => a - b);
    return qs.map((q) => sample[Math.min(sample.length - 1, Math.floor(q * sample.length))]);
  }

  #robustRange() {
    const [lo, hi] = this.#percentiles([0.01, 0.99]);
    return hi - lo < 0.2 ? [lo - 0.1, hi + 0.1] : [lo, hi];
  }

  #rebuildAttributes() {
    this.colours = new Float32Array(this.positions.array.length);
    this.geometry.setAttribute("position", new THREE.BufferAttribute(this.positions.array, 3));
    this.geometry.setAttribute("color", new THREE.BufferAttribute(this.colours, 3));
    this.#colourRange(0, this.positions.count);
    this.#upload(0);
  }

  #recolour() {
    if (this.positions.count && this.colourMode === "height") {
      for (let i = 0; i < this.positions.count; i++) {
        const a = this.positions.array;
        this.heights.array[i] = a[3 * i] * this.up.x + a[3 * i + 1] * this.up.y + a[3 * i + 2] * this.up.z;
      }
      this.range = this.#robustRange();
    }
    this.#colourRange(0, this.positions.count);
    this.#upload(0);
    this.dirty = true;
  }

  #colourRange(start, end) {
    const [lo, hi] = this.range ?? [0, 1];
    for (let i = start; i < end; i++) {
      let rgb;
      if (this.colourMode === "height") rgb = turbo((this.heights.array[i] - lo) / (hi - lo || 1));
      else rgb = [this.rgb.array[3 * i] / 255, this.rgb.array[3 * i + 1] / 255, this.rgb.array[3 * i + 2] / 255];
      this.colours.set(rgb, 3 * i);
    }
  }

  #upload(from) {
    const position = this.geometry.getAttribute("position");
    const colour = this.geometry.getAttribute("color");
    for (const attribute of [position, colour]) {
      attribute.clearUpdateRanges();
      attribute.addUpdateRange(from * 3, (this.positions.count - from) * 3);
      attribute.needsUpdate = true;
    }
    this.geometry.setDrawRange(0, this.positions.count);
    this.geometry.boundingSphere = null;
  }

  #listen() {
    let down = null;
    const active = new Set(); // pointers down: a pinch or two-finger pan is no tap
    const el = this.renderer.domElement;
    el.addEventListener("pointerdown", (e) => {
      active.add(e.pointerId);
      down = active.size === 1 ? { x: e.clientX, y: e.clientY, t: performance.now(), id: e.pointerId } : null;
    });
    el.addEventListener("pointerup", (e) => {
      active.delete(e.pointerId);
      if (!down || down.id !== e.pointerId) return;
      const tap = Math.hypot(e.clientX - down.x, e.clientY - down.y) < TAP_MAX_MOVE_PX &&
        performance.now() - down.t < TAP_MAX_MS;
      down = null;
      if (!tap) return;
      const picked = this.pick(e.clientX, e.clientY);
      if (picked) this.onPick?.(picked, e);
    });
    el.addEventListener("pointercancel", (e) => {
      active.delete(e.pointerId);
      down = null;
    });
  }
}
