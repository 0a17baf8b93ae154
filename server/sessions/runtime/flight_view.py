"""The frames the drone is told in: the simulator's flight frame and the client's world.

The simulator works in a gravity-aligned flight frame (z up, metres); the session's world frame
is the first camera's frame, whose axes need not be level. ``flight_frame`` gives the rotation
between the two. After a loop correction the tracker's world (the client's) runs ahead of the
simulation's until the map is rebuilt in the corrected world (seconds later): ``FlightView``
keeps that difference (``T_view_sim``), so that everything the drone reports goes out in the
client's world and every target comes in from it, and the drone stays where it was relative to
the camera meanwhile.
"""

from __future__ import annotations

import threading

import numpy as np

from server.geometry import invert


def flight_frame(gravity_world: np.ndarray | None) -> np.ndarray:
    """R_flight_world (3x3): flight z is against gravity, flight x the first camera's optical
    axis made level. gravity_world: gravity's direction in the world (= first camera) frame;
    None means +y, a camera held upright and level."""
    g = np.array([0.0, 1.0, 0.0]) if gravity_world is None else np.asarray(gravity_world, float)
    up = -g / np.linalg.norm(g)
    for forward in (np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0])):
        x = forward - forward.dot(up) * up
        if np.linalg.norm(x) > 1e-3:  # the camera looked straight up or down: use its x axis
            break
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(up, x), up])


class FlightView:
    """Maps between the flight frame and the client's world (module docstring). Thread-safe:
    its own lock, held only to read or compose ``T_view_sim``, taking no other under it."""

    def __init__(self, gravity_world: np.ndarray | None) -> None:
        self.R_flight_world = flight_frame(gravity_world)
        self.T_world_flight = np.eye(4)  # constant: the state at 20 Hz needs it
        self.T_world_flight[:3, :3] = self.R_flight_world.T
        # The client's world from the simulation's (4x4, metres): the loop corrections the
        # tracker has taken (map_corrected went out, poses come in the corrected world) that the
        # drone and its map have not yet.
        self._T_view_sim = np.eye(4)
        self._lock = threading.Lock()

    @property
    def T_view_sim(self) -> np.ndarray:
        with self._lock:
            return self._T_view_sim.copy()

    def T_world_flight_shown(self) -> np.ndarray:
        """T_world_flight (4x4, metres) into the client's world: the tracker's, which may be
        ahead of the simulation's by loop corrections not yet rebuilt into the map."""
        with self._lock:
            return self._T_view_sim @ self.T_world_flight

    def to_flight(self, p_world: np.ndarray) -> np.ndarray:
        """A point (3,) of the client's world in the flight frame."""
        T = invert(self.T_world_flight_shown())
        return T[:3, :3] @ np.asarray(p_world, dtype=np.float64) + T[:3, 3]

    def to_world(self, p_flight: np.ndarray) -> np.ndarray:
        """Flight-frame points ((3,) or (N, 3)) in the client's world."""
        T = self.T_world_flight_shown()
        return np.asarray(p_flight, dtype=np.float64) @ T[:3, :3].T + T[:3, 3]

    def motion_in_flight(
        self, centres: np.ndarray, velocities: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """(K, 3) centres (metres) and velocities (m/s) in the client's world -> the same in
        the flight frame."""
        T = invert(self.T_world_flight_shown())
        R = T[:3, :3]
        return np.reshape(centres, (-1, 3)) @ R.T + T[:3, 3], np.reshape(velocities, (-1, 3)) @ R.T

    def direction_to_world(self, v_flight: np.ndarray) -> np.ndarray:
        """Flight-frame directions or velocities ((3,) or (N, 3)) in the client's world."""
        return np.asarray(v_flight, dtype=np.float64) @ self.T_world_flight_shown()[:3, :3].T

    def tracker_corrected(self, T_correction: np.ndarray) -> None:
        """The tracker moved into a corrected world: ``T_correction`` (4x4, world frame,
        metres) maps the old world into the new one; the simulation has not moved yet."""
        with self._lock:
            self._T_view_sim = np.asarray(T_correction, dtype=np.float64) @ self._T_view_sim

    def flight_delta(self, T_move: np.ndarray) -> np.ndarray:
        """A world move ``T_move`` (4x4, world frame, metres) in the flight frame."""
        return invert(self.T_world_flight) @ T_move @ self.T_world_flight

    def simulation_moved(self, T_move: np.ndarray) -> None:
        """The simulation moved into the corrected world by ``T_move`` (4x4, world frame,
        metres): what the client saw moved into the simulation itself."""
        with self._lock:
            self._T_view_sim = self._T_view_sim @ invert(T_move)
