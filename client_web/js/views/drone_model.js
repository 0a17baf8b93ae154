// The virtual drone as three.js primitives, in its body frame (x forward, y left, z up, metres):
// a body, four arms, four motors with spinning rotors, a nose light, and the ground marker that
// makes its height readable in AR.

import * as THREE from "three";

export const DRONE_COLOUR = 0xff00cc; // bright magenta: rare in rooms, easy to find in a picture
// The airframe the simulator flies (server/simulation/config.py): arms of arm_length_m, and
// rotors whose tips reach its collision sphere (radius_m, 0.12 m) and no further, so that what
// touches a wall on screen is what collides (shared/PROTOCOL.md, "The drone").
const ARM_LENGTH = 0.09; // centre to motor, metres (a 0.18 m wheelbase)
const ROTOR_RADIUS = 0.03; // ARM_LENGTH + ROTOR_RADIUS = the collision radius, 0.12 m

function mesh(geometry, material, position = [0, 0, 0]) {
  const m = new THREE.Mesh(geometry, material);
  m.position.set(...position);
  return m;
}

/** A small quadrotor. `update(dt, spinning)` turns the rotors. `colour`, `emissive`: its paint
 * (another pilot's drone in a shared room wears another colour: room_pilots.js). */
export function createDrone({ colour = DRONE_COLOUR, emissive = 0x8a0070 } = {}) {
  const drone = new THREE.Group();
  drone.name = "drone";
  const paint = new THREE.MeshLambertMaterial({ color: colour, emissive });
  const dark = new THREE.MeshLambertMaterial({ color: 0x222222, emissive: 0x111111 });
  const bladeMat = new THREE.MeshBasicMaterial({ color: 0xffffff, transparent: true, opacity: 0.85 });
  const discMat = new THREE.MeshBasicMaterial({
    color: 0xffffff, transparent: true, opacity: 0.18, side: THREE.DoubleSide, depthWrite: false,
  });

  drone.add(mesh(new THREE.BoxGeometry(0.13, 0.085, 0.045), paint)); // body
  drone.add(mesh(new THREE.BoxGeometry(0.05, 0.06, 0.02), dark, [-0.02, 0, 0.032])); // battery
  const nose = mesh(new THREE.SphereGeometry(0.018, 12, 8), new THREE.MeshBasicMaterial({ color: 0x00ff66 }),
    [0.07, 0, 0]); // forward light
  drone.add(nose);

  const rotors = [];
  for (let k = 0; k < 4; k++) {
    const angle = Math.PI / 4 + (k * Math.PI) / 2; // arms on the diagonals: X configuration
    const dir = new THREE.Vector3(Math.cos(angle), Math.sin(angle), 0);
    const arm = mesh(new THREE.BoxGeometry(ARM_LENGTH, 0.022, 0.016), paint);
    arm.position.copy(dir.clone().multiplyScalar(ARM_LENGTH / 2));
    arm.rotation.z = angle;
    drone.add(arm);
    const tip = dir.clone().multiplyScalar(ARM_LENGTH);
    const motor = mesh(new THREE.CylinderGeometry(0.014, 0.014, 0.03, 14), dark);
    motor.rotation.x = Math.PI / 2; // cylinder axis (y) -> body z
    motor.position.copy(tip).setZ(0.01);
    drone.add(motor);
    const rotor = new THREE.Group();
    rotor.position.copy(tip).setZ(0.032);
    const disc = mesh(new THREE.CircleGeometry(ROTOR_RADIUS, 24), discMat);
    rotor.add(disc);
    const blade = mesh(new THREE.BoxGeometry(2 * ROTOR_RADIUS, 0.012, 0.003), bladeMat);
    rotor.add(blade);
    rotor.userData.direction = k % 2 === 0 ? 1 : -1;
    drone.add(rotor);
    rotors.push(rotor);
  }
  drone.userData.rotors = rotors;
  drone.userData.update = (dt, spinning) => {
    for (const rotor of rotors) rotor.rotation.z += (spinning ? 60 : 0) * dt * rotor.userData.direction;
  };
  return drone;
}

/** A soft shadow with a ring, lying in the x-y plane (give it the ground's orientation), and
 * a thin vertical line from it up to the drone (set its length with setHeight). */
export function createGroundMarker() {
  const marker = new THREE.Group();
  marker.name = "ground-marker";
  const shadow = mesh(new THREE.CircleGeometry(0.14, 32), new THREE.MeshBasicMaterial({
    color: 0x000000, transparent: true, opacity: 0.45, depthWrite: false, side: THREE.DoubleSide,
  }));
  const ring = mesh(new THREE.RingGeometry(0.15, 0.18, 40), new THREE.MeshBasicMaterial({
    color: 0x00e5ff, transparent: true, opacity: 0.9, depthWrite: false, side: THREE.DoubleSide,
  }));
  marker.add(shadow, ring);
  const stem = new THREE.Line(
    new THREE.BufferGeometry().setFromPoints([new THREE.Vector3(0, 0, 0), new THREE.Vector3(0, 0, 1)]),
    new THREE.LineDashedMaterial({ color: 0x00e5ff, dashSize: 0.04, gapSize: 0.03, transparent: true, opacity: 0.8 }),
  );
  stem.computeLineDistances();
  marker.add(stem);
  marker.userData.setHeight = (h) => {
    stem.scale.set(1, 1, Math.max(h, 1e-3));
    stem.visible = h > 0.02;
  };
  return marker;
}

/** A target marker: a vertical pin with a ring, in the x-y plane like the ground marker. */
export function createTargetMarker() {
  const marker = new THREE.Group();
  marker.name = "target";
  const material = new THREE.MeshBasicMaterial({ color: 0xffd400, transparent: true, opacity: 0.9, side: THREE.DoubleSide });
  marker.add(mesh(new THREE.RingGeometry(0.06, 0.09, 32), material));
  marker.add(mesh(new THREE.SphereGeometry(0.03, 12, 8), material));
  return marker;
}
