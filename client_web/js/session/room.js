// A shared room's phones (PROTOCOL.md, "A shared room"; the `room` message): who flies in the
// room with this session, where their drones and cameras are. The server sends the message
// about 5 times a second while the room has two or more live phones, and stops when it has
// fewer: a room not heard of for STALE_MS is gone from the page (its drones would stand still).

export const STALE_MS = 3000;

/** 7 numbers [x, y, z, qx, qy, qz, qw] of a flat list, or null when they are all zero. */
function poseAt(flat, index) {
  const pose = flat.slice(7 * index, 7 * index + 7);
  if (pose.length < 7 || pose.every((v) => v === 0)) return null;
  return { position: pose.slice(0, 3), quaternion: pose.slice(3, 7) };
}

/** A pilot's place in the room's race (the message's race_* lists), or null: no race. */
function raceOf(message, index) {
  if (!message.race) return null;
  return { passed: message.race_passed[index] ?? 0, missed: message.race_missed[index] ?? 0,
    time: message.race_time_s[index] ?? 0, finished: message.race_finished[index] === true,
    rank: message.race_rank[index] ?? 0 };
}

/** Each pilot's route ahead (the message's route_lengths and routes): a flat [x, y, z, ...]
 * list per pilot, null where it flies none (two points at least make a route). */
function routesOf(message) {
  const lengths = message.route_lengths ?? [];
  const routes = [];
  let at = 0;
  for (const n of lengths) {
    routes.push(n >= 2 ? message.routes.slice(3 * at, 3 * (at + n)) : null);
    at += n;
  }
  return routes;
}

/**
 * A `room` message as plain data: {you, pilots: [{index, name, you, placed, mode, drone,
 * camera, route, race}], race}; drone and camera are {position, quaternion} in the room's world
 * frame, or null (no drone: mode "none"; not placed: no camera); route: the drone's route ahead,
 * flat [x, y, z, ...] in the world frame, or null. race: {state (countdown, running,
 * finished), number, startsIn (s), gates} and each pilot's {passed, missed, time, finished,
 * rank}, or null without a race.
 */
export function roomPilots(message) {
  const routes = routesOf(message);
  const pilots = message.pilots.map((name, index) => {
    const mode = message.modes[index] ?? "none";
    const placed = message.placed[index] === true;
    return { index, name, you: index === message.you, placed, mode,
      drone: mode === "none" ? null : poseAt(message.drones, index),
      camera: placed ? poseAt(message.cameras, index) : null,
      route: mode === "none" ? null : routes[index] ?? null, race: raceOf(message, index) };
  });
  const race = message.race ? { state: message.race, number: message.race_number,
    startsIn: message.race_starts_in_s, gates: message.race_gates } : null;
  return { you: message.you, pilots, race };
}

/** A pilot's name as the page shows it: the hello's client_name, else its place in the room. */
export function pilotLabel(pilot) {
  return pilot.name || (pilot.index === 0 ? "owner" : `phone ${pilot.index + 1}`);
}
