// The other pilots of a shared room (session/room.js), drawn in a view: each one's drone, in a
// colour of its own (this page's drone keeps the magenta paint), the route it flies (a line in
// its colour), and, where asked (the map), its phone's camera as a small frustum. One group in the world frame: the map view adds it to
// its scene, the AR view to its `world` group (moved with the shown frame). Objects follow the
// pilot's index in the room; a pilot that leaves, or whose drone has no mode ("none"), loses
// its drone at the next update.

import * as THREE from "three";
import { createDrone } from "./drone_model.js";
import { projectPoint } from "./geometry.js";

// Paint per other pilot (by index in the room): far from the own drone's magenta and from each
// other, bright enough on a camera picture and on the map's dark background.
const COLOURS = [
  { colour: 0x00c8ff, emissive: 0x005a80 }, // sky blue
  { colour: 0xff9a00, emissive: 0x804000 }, // orange
  { colour: 0x7cff00, emissive: 0x3a7a00 }, // lime
  { colour: 0xffe600, emissive: 0x807000 }, // yellow
];
export const pilotColour = (index) => COLOURS[index % COLOURS.length].colour;

/** A small camera frustum (OpenCV camera frame: z forward, y down), as the map's own camera. */
function createFrustum(colour) {
  const c = [0, 0, 0];
  const corners = [[-0.1, -0.075, 0.13], [0.1, -0.075, 0.13], [0.1, 0.075, 0.13], [-0.1, 0.075, 0.13]];
  const segments = [];
  corners.forEach((q, i) => segments.push(c, q, q, corners[(i + 1) % 4]));
  const geometry = new THREE.BufferGeometry().setFromPoints(segments.map((v) => new THREE.Vector3(...v)));
  const frustum = new THREE.LineSegments(geometry, new THREE.LineBasicMaterial({ color: colour }));
  frustum.matrixAutoUpdate = false;
  return frustum;
}

/** The line of a pilot's route, in its colour (the own route is yellow: map_view.js). */
function createRouteLine(colour) {
  const line = new THREE.Line(new THREE.BufferGeometry(), new THREE.LineBasicMaterial({ color: colour }));
  line.frustumCulled = false;
  line.matrixAutoUpdate = false; // its points are in the world frame
  return line;
}

function pointsOf(flat) {
  const points = [];
  for (let i = 0; i + 2 < flat.length; i += 3) points.push(new THREE.Vector3(flat[i], flat[i + 1], flat[i + 2]));
  return points;
}

function poseMatrix({ position, quaternion }) {
  return new THREE.Matrix4().compose(new THREE.Vector3(...position), new THREE.Quaternion(...quaternion),
    new THREE.Vector3(1, 1, 1));
}

export class RoomPilots {
  /** @param {{cameras?: boolean, halo?: boolean}} options cameras: draw the other phones'
   * camera frusta; halo: a sphere the size of the drone's collision radius around each drone */
  constructor({ cameras = false, halo = false } = {}) {
    this.group = new THREE.Group();
    this.group.name = "room-pilots";
    this.cameras = cameras;
    this.halo = halo;
    this.drones = new Map(); // pilot index -> drone Object3D
    this.frusta = new Map(); // pilot index -> camera frustum
    this.routes = new Map(); // pilot index -> its route's line
    this.room = null;
  }

  /** The room's pilots now (roomPilots' answer), or null: no room. Returns whether anything
   * drawn changed. */
  set(room) {
    this.room = room;
    const others = (room?.pilots ?? []).filter((p) => !p.you);
    const withDrone = new Map(others.filter((p) => p.drone).map((p) => [p.index, p]));
    const withCamera = new Map(this.cameras ? others.filter((p) => p.camera).map((p) => [p.index, p]) : []);
    let changed = this.#sync(this.drones, withDrone, (p) => this.#makeDrone(p.index), (object, p) => {
      object.matrix.copy(poseMatrix(p.drone));
      object.userData.spinning = !["landed", "crashed", "faulted"].includes(p.mode);
    });
    changed = this.#sync(this.frusta, withCamera, (p) => createFrustum(pilotColour(p.index)),
      (object, p) => object.matrix.copy(poseMatrix(p.camera))) || changed;
    const withRoute = new Map(others.filter((p) => p.route).map((p) => [p.index, p]));
    changed = this.#sync(this.routes, withRoute, (p) => createRouteLine(pilotColour(p.index)), (line, p) => {
      line.geometry.dispose();
      line.geometry = new THREE.BufferGeometry().setFromPoints(pointsOf(p.route));
    }) || changed;
    return changed || withDrone.size > 0 || withCamera.size > 0 || withRoute.size > 0;
  }

  /** Add, move and remove objects so that `objects` holds one per entry of `wanted`. */
  #sync(objects, wanted, make, place) {
    let changed = false;
    for (const [index, object] of objects) {
      if (wanted.has(index)) continue;
      this.group.remove(object);
      object.traverse((o) => {
        o.geometry?.dispose();
      });
      objects.delete(index);
      changed = true;
    }
    for (const [index, pilot] of wanted) {
      let object = objects.get(index);
      if (!object) {
        object = make(pilot);
        objects.set(index, object);
        this.group.add(object);
        changed = true;
      }
      place(object, pilot);
      object.matrixWorldNeedsUpdate = true;
    }
    return changed;
  }

  #makeDrone(index) {
    const paint = COLOURS[index % COLOURS.length];
    const drone = createDrone(paint);
    drone.name = `room-drone-${index}`;
    drone.matrixAutoUpdate = false;
    if (this.halo) {
      drone.add(new THREE.Mesh(new THREE.SphereGeometry(0.12, 16, 10),
        new THREE.MeshBasicMaterial({ color: paint.colour, transparent: true, opacity: 0.15, depthWrite: false })));
    }
    return drone;
  }

  /** Whether a rotor turns (the view redraws while one does). */
  get spinning() {
    for (const drone of this.drones.values()) if (drone.userData.spinning) return true;
    return false;
  }

  /** Turn the rotors of the drones in the air. */
  update(dt) {
    for (const drone of this.drones.values()) drone.userData.update(dt, drone.userData.spinning);
  }

  /** The drones drawn, for the page's snapshot: [{index, name, mode, position}]; with a camera
   * (T_camera_world, OpenCV, a THREE.Matrix4) and its intrinsics, each drone's centre in that
   * camera (cameraPoint) and its pixel (null behind the camera). */
  drawn({ T_camera_world = null, intrinsics = null } = {}) {
    const out = [];
    for (const [index, drone] of this.drones) {
      const pilot = this.room?.pilots[index];
      const position = new THREE.Vector3().setFromMatrixPosition(drone.matrix);
      const item = { index, name: pilot?.name ?? "", mode: pilot?.mode ?? "none", position: position.toArray() };
      if (T_camera_world && intrinsics) {
        const p = position.clone().applyMatrix4(T_camera_world);
        item.cameraPoint = p.toArray();
        item.pixel = projectPoint(intrinsics, item.cameraPoint);
      }
      out.push(item);
    }
    return out;
  }

  /** The other pilots' routes drawn: [{index, points: [[x, y, z], ...]}] (world frame). */
  routesDrawn() {
    return [...this.routes].map(([index, line]) => {
      const a = line.geometry.getAttribute("position");
      return { index, points: Array.from({ length: a.count }, (_, i) => [a.getX(i), a.getY(i), a.getZ(i)]) };
    });
  }

  /** The other phones' cameras drawn: [{index, position}]. */
  camerasDrawn() {
    return [...this.frusta].map(([index, f]) => ({ index, position: new THREE.Vector3().setFromMatrixPosition(f.matrix).toArray() }));
  }
}
