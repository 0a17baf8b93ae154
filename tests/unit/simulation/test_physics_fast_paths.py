"""The physics loop's plain-float paths give what the numpy ones give, to the bit: the distance
field at one point (``FlightMap.distance_at``) and a chunk's contact check
(``contact.first_contact``), against the vectorised queries they stand in for."""

from __future__ import annotations

import numpy as np
import pytest

from server.simulation.config import SimulationConfig
from server.simulation.contact import first_contact
from server.simulation.flight_map import FlightMap
from server.simulation.scenes import box_in_the_way, room_with_door

CONFIG = SimulationConfig()


@pytest.mark.parametrize(
    "flight_map",
    [
        room_with_door(CONFIG.voxel_m).flight_map,
        box_in_the_way(CONFIG.voxel_m, unknown_is_free=True).flight_map,
        FlightMap(CONFIG.voxel_m),  # no grid yet: everything outside
    ],
)
def test_the_distance_at_one_point_is_the_fields_to_the_bit(flight_map):
    rng = np.random.default_rng(5)
    box = flight_map.bounds
    points = rng.uniform(box.lo - 1.5, box.hi + 1.5, size=(5000, 3))  # outside the grid too
    v = flight_map.voxel_m
    points[:500] = np.round(points[:500] / v) * v  # on cell corners
    points[500:1000] = np.round(points[500:1000] / v) * v + 0.5 * v  # on cell centres
    expected = flight_map.distance(points)
    got = np.array([flight_map.distance_at(x, y, z) for x, y, z in points.tolist()])
    np.testing.assert_array_equal(got.view(np.int64), expected.view(np.int64))


def first_contact_vectorised(flight_map, track, radius_m):
    """The numpy check first_contact replaced: all distances of the chunk in one query."""
    d = flight_map.distance(track)
    touching = (d[1:] < radius_m) & (d[1:] < d[:-1])
    long = np.linalg.norm(np.diff(track, axis=0), axis=1) > 0.5 * radius_m
    if long.any():
        touching[long] |= ~flight_map.segments_free(track[:-1][long], track[1:][long], radius_m)
    return int(np.argmax(touching)) if touching.any() else None


def test_a_chunks_contact_check_finds_the_step_the_vectorised_one_finds():
    flight_map = room_with_door(CONFIG.voxel_m).flight_map
    rng = np.random.default_rng(8)
    found = 0
    for _ in range(400):
        # 17 positions of a chunk near the wall at x = 1.9, at up to 4 m/s, some steps long.
        start = rng.uniform([1.45, 0.2, 0.3], [1.85, 2.8, 2.1])
        steps = rng.normal(size=(16, 3)) * rng.choice([0.002, 0.01, 0.05])
        steps[:, 0] = np.abs(steps[:, 0])  # towards the wall
        track = np.vstack([start, start + np.cumsum(steps, axis=0)])
        expected = first_contact_vectorised(flight_map, track, CONFIG.radius_m)
        got = first_contact(flight_map, [tuple(p) for p in track.tolist()], CONFIG.radius_m)
        assert got == expected
        found += expected is not None
    assert 50 < found < 350  # both kinds of chunk were checked
