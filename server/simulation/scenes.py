"""Synthetic flight scenes built from boxes, for tests: a room split by a wall with a door, an
L-shaped corridor, a box in the way, a sealed room.

Every scene is closed by 0.1 m walls, floor and ceiling (explicit boxes, so it reads the same
whether unknown space counts as free or not), and knows its exact geometry: ``true_distance``
measures against the boxes themselves, not the grid.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from server.geometry.arrays import FloatArray
from server.simulation.flight_map import FlightMap

WALL_M = 0.1  # thickness of the enclosing walls, floor and ceiling


@dataclass
class Scene:
    """A flight map with its boxes and a suggested start and goal (flight frame, metres)."""

    name: str
    flight_map: FlightMap
    boxes: list[tuple[FloatArray, FloatArray]]
    start: FloatArray
    goal: FloatArray

    def true_distance(self, points: FloatArray) -> FloatArray:
        """(N,) exact distance from points (N, 3) to the nearest box (0 inside one)."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        best = np.full(len(p), np.inf)
        for lo, hi in self.boxes:
            gap = np.maximum(np.maximum(lo - p, p - hi), 0.0)
            best = np.minimum(best, np.linalg.norm(gap, axis=1))
        return best


def _enclosure(size: Sequence[float]) -> list[tuple[FloatArray, FloatArray]]:
    """Walls, floor and ceiling around the interior [0, size]."""
    sx, sy, sz = size
    t = WALL_M
    return [
        (np.array([-t, -t, -t]), np.array([sx + t, sy + t, 0.0])),  # floor
        (np.array([-t, -t, sz]), np.array([sx + t, sy + t, sz + t])),  # ceiling
        (np.array([-t, -t, 0.0]), np.array([0.0, sy + t, sz])),  # x = 0
        (np.array([sx, -t, 0.0]), np.array([sx + t, sy + t, sz])),  # x = sx
        (np.array([0.0, -t, 0.0]), np.array([sx, 0.0, sz])),  # y = 0
        (np.array([0.0, sy, 0.0]), np.array([sx, sy + t, sz])),  # y = sy
    ]


def _scene(
    name: str,
    size: Sequence[float],
    inner: Sequence[tuple[ArrayLike, ArrayLike]],
    start: ArrayLike,
    goal: ArrayLike,
    voxel_m: float,
    unknown_is_free: bool,
) -> Scene:
    boxes = _enclosure(size) + [(np.asarray(lo, float), np.asarray(hi, float)) for lo, hi in inner]
    lo, hi = -WALL_M * np.ones(3), np.asarray(size, float) + WALL_M
    flight_map = FlightMap.from_boxes(lo, hi, boxes, voxel_m, unknown_is_free)
    return Scene(name, flight_map, boxes, np.asarray(start, float), np.asarray(goal, float))


def room_with_door(
    voxel_m: float = 0.05, unknown_is_free: bool = False, door_y: tuple[float, float] = (1.2, 2.1)
) -> Scene:
    """A 4 x 3 x 2.4 m room split at x = 2 by a 0.2 m wall with a door 2 m high spanning
    ``door_y`` (default 0.9 m wide); start and goal on either side, away from the door."""
    (y0, y1), h = door_y, 2.0
    wall = [
        ((1.9, 0.0, 0.0), (2.1, y0, 2.4)),
        ((1.9, y1, 0.0), (2.1, 3.0, 2.4)),
        ((1.9, y0, h), (2.1, y1, 2.4)),
    ]
    return _scene(
        "room_with_door",
        (4.0, 3.0, 2.4),
        wall,
        (1.0, 0.6, 1.2),
        (3.0, 0.6, 1.2),
        voxel_m,
        unknown_is_free,
    )


def corridor(voxel_m: float = 0.05, unknown_is_free: bool = False) -> Scene:
    """An L-shaped corridor 1 m wide and 2 m high: along x at y in [0, 1], then along y at
    x in [3, 4]; start and goal at its two ends."""
    block = [((0.0, 1.0, 0.0), (3.0, 4.0, 2.0))]
    return _scene(
        "corridor",
        (4.0, 4.0, 2.0),
        block,
        (0.4, 0.5, 1.0),
        (3.5, 3.6, 1.0),
        voxel_m,
        unknown_is_free,
    )


def box_in_the_way(voxel_m: float = 0.05, unknown_is_free: bool = False) -> Scene:
    """A 5 x 3 x 2.4 m room with a 1 x 1.6 x 1.8 m box on the floor on the straight line from
    start to goal."""
    box = [((2.0, 0.7, 0.0), (3.0, 2.3, 1.8))]
    return _scene(
        "box_in_the_way",
        (5.0, 3.0, 2.4),
        box,
        (1.0, 1.5, 1.0),
        (4.0, 1.5, 1.0),
        voxel_m,
        unknown_is_free,
    )


def sealed_room(voxel_m: float = 0.05, unknown_is_free: bool = False) -> Scene:
    """A 5 x 4 x 2.4 m room holding a closed 1.4 x 1.8 x 1.6 m box with 0.1 m walls and free
    space inside; the goal is inside it, unreachable from the start outside."""
    lo, hi, t = np.array([3.2, 1.0, 0.0]), np.array([4.6, 2.8, 1.6]), WALL_M
    shell = [
        (lo, np.array([hi[0], hi[1], lo[2] + t])),
        (np.array([lo[0], lo[1], hi[2] - t]), hi),
        (lo, np.array([lo[0] + t, hi[1], hi[2]])),
        (np.array([hi[0] - t, lo[1], lo[2]]), hi),
        (lo, np.array([hi[0], lo[1] + t, hi[2]])),
        (np.array([lo[0], hi[1] - t, lo[2]]), hi),
    ]
    return _scene(
        "sealed_room",
        (5.0, 4.0, 2.4),
        shell,
        (1.0, 2.0, 1.2),
        (3.9, 1.9, 0.8),
        voxel_m,
        unknown_is_free,
    )


SCENES = {
    "room_with_door": room_with_door,
    "corridor": corridor,
    "box_in_the_way": box_in_the_way,
    "sealed_room": sealed_room,
}
