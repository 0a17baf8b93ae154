"""The other drones of a shared room as obstacles for this drone's contact checks.

Each phone's drone is simulated in its own session, so the others are known only as the web
process last heard of them (a few times a second): spheres of the drone's own radius at those
positions, carried on at their velocity for a short while. For contact they are part of the
distance field: the distance to the nearest blocked space becomes the least of the map's and
the distance to each other drone's sphere, which keeps the field 1-Lipschitz, so the physics
loop's chunking and every touch rule (bump, crash, by the speed into the surface: contact.py)
hold for a drone as for a wall. What the other drone does is its own session's: it bumps or
crashes when its own physics meets this drone's sphere. The speed judged is this drone's own
(the other is taken as still over the step), and a drone holding still (stillness.py) runs no
steps, so it is bumped only when it moves. Routes are planned on the map alone: drones move.

Flight frame, metres.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

from server.geometry.arrays import BoolArray, FloatArray
from server.simulation.config import SimulationConfig
from server.simulation.flight_map import FlightMap

# The others' positions are carried on at their velocity for at most this long after they
# were heard of: beyond it, a drone that stopped reporting stays where it was last.
CARRY_ON_S = 0.3


class OtherDrones:
    """Where the other drones of the room are: ``set`` with their centres and velocities
    (flight frame) as heard at a time, ``at(t)`` their centres then."""

    def __init__(self, radius_m: float) -> None:
        self.radius_m = radius_m
        self._centres = np.empty((0, 3))
        self._velocities = np.empty((0, 3))
        self._heard_s = 0.0

    def set(self, centres: ArrayLike, velocities: ArrayLike, heard_s: float) -> None:
        """centres, velocities: (K, 3) metres and m/s; heard_s: when (a monotonic clock)."""
        self._centres = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
        self._velocities = np.asarray(velocities, dtype=np.float64).reshape(-1, 3)
        self._heard_s = heard_s

    def at(self, now_s: float) -> FloatArray:
        """(K, 3) centres at ``now_s``, carried on from when they were heard of."""
        dt = min(max(0.0, now_s - self._heard_s), CARRY_ON_S)
        return self._centres + dt * self._velocities

    def __len__(self) -> int:
        return len(self._centres)


class WithDrones:
    """``flight_map``'s distance field with spheres of ``radius_m`` at ``centres`` (K, 3)
    blocked too: the queries contact.py makes (``distance_at``, ``distance``, ``gradient``,
    ``segments_free``); everything else is the map's."""

    def __init__(self, flight_map: FlightMap, centres: FloatArray, radius_m: float) -> None:
        self.flight_map = flight_map
        self.centres = centres
        self.radius_m = radius_m
        self._plain = [(float(x), float(y), float(z)) for x, y, z in centres]

    def __getattr__(self, name: str) -> object:
        return getattr(self.flight_map, name)

    def distance_at(self, x: float, y: float, z: float) -> float:
        d = self.flight_map.distance_at(x, y, z)
        for cx, cy, cz in self._plain:
            dx, dy, dz = x - cx, y - cy, z - cz
            d = min(d, math.sqrt(dx * dx + dy * dy + dz * dz) - self.radius_m)
        return d

    def _spheres(self, points: FloatArray) -> tuple[FloatArray, FloatArray]:
        """(..., K) distance of ``points`` (..., 3) to each sphere's surface, and the offsets
        (..., K, 3) from each centre."""
        offsets = points[..., None, :] - self.centres
        return np.linalg.norm(offsets, axis=-1) - self.radius_m, offsets

    def distance(self, points: ArrayLike) -> FloatArray:
        p = np.asarray(points, dtype=np.float64)
        d = self.flight_map.distance(p)
        if len(self.centres):
            d = np.minimum(d, self._spheres(p)[0].min(axis=-1))
        return d

    def gradient(self, points: ArrayLike) -> FloatArray:
        """Where a sphere is nearer than the map, the unit direction away from its centre."""
        p = np.asarray(points, dtype=np.float64)
        g = self.flight_map.gradient(p)
        if len(self.centres):
            to_spheres, offsets = self._spheres(p)
            nearest = to_spheres.argmin(axis=-1)
            closer = np.take_along_axis(to_spheres, nearest[..., None], -1)[..., 0] < (
                self.flight_map.distance(p)
            )
            away = np.take_along_axis(offsets, nearest[..., None, None], -2)[..., 0, :]
            length = np.linalg.norm(away, axis=-1, keepdims=True)
            away = np.divide(away, length, out=np.zeros_like(away), where=length > 1e-9)
            g = np.where(closer[..., None], away, g)
        return np.asarray(g)

    def segments_free(self, a: ArrayLike, b: ArrayLike, radius_m: float = 0.0) -> BoolArray:
        """The map's ``segments_free``, and each segment's least distance to every centre at
        least radius_m + the spheres' radius."""
        a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
        free = self.flight_map.segments_free(a, b, radius_m)
        if len(self.centres):
            ab = b - a
            length2 = np.maximum((ab * ab).sum(axis=-1), 1e-12)
            to_c = self.centres[None, :, :] - a[:, None, :]  # (M, K, 3)
            t = np.clip((to_c * ab[:, None, :]).sum(axis=-1) / length2[:, None], 0.0, 1.0)
            closest = a[:, None, :] + t[..., None] * ab[:, None, :]
            gap = np.linalg.norm(closest - self.centres[None], axis=-1).min(axis=-1)
            free = free & (gap >= radius_m + self.radius_m)
        return np.asarray(free)


def clear_of_drones(
    flight_map: FlightMap,
    point: FloatArray,
    centres: FloatArray,
    config: SimulationConfig,
    reach_m: float,
    step_m: float = 0.1,
) -> FloatArray | None:
    """``point`` (flight frame, metres; free in the map) when no other drone's sphere is within
    a planning radius of this drone's there, else the nearest point that is, and has the
    map's planning clearance, on a grid of ``step_m`` within ``reach_m`` of ``point``; None
    when there is none (a room's drones fill the space). Where a drone appears (its spawn,
    a race's restart), so that it does not appear inside another."""
    centres = np.asarray(centres, dtype=float).reshape(-1, 3)
    apart = config.radius_m + config.planning_radius_m  # sphere to sphere, with the margin
    n = int(reach_m / step_m)
    axis = np.arange(-n, n + 1) * step_m
    grid = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), axis=-1).reshape(-1, 3)
    grid = grid[np.linalg.norm(grid, axis=1) <= reach_m]
    grid = grid[np.argsort(np.linalg.norm(grid, axis=1), kind="stable")]
    candidates = point + grid
    far = np.linalg.norm(candidates[:, None, :] - centres[None], axis=2).min(axis=1) >= apart
    candidates = candidates[far]
    if len(candidates) == 0:
        return None
    if far[0]:  # the point itself (offset 0 comes first)
        return np.array(point, dtype=float)
    clear = flight_map.distance(candidates) >= config.planning_radius_m
    return np.array(candidates[np.argmax(clear)]) if clear.any() else None
