"""The other drones of a shared room as spheres this drone touches (server.simulation.
other_drones): the same bump and crash rules as for the map, by the speed into the other
drone; a distance field that stays the map's away from them."""

from __future__ import annotations

import numpy as np
import pytest

from server.simulation.config import SimulationConfig
from server.simulation.drone import DroneSimulator
from server.simulation.drone_types import DroneCommandError, DroneEventKind, DroneMode
from server.simulation.other_drones import CARRY_ON_S, OtherDrones, WithDrones
from server.simulation.scenes import room_with_door

CONFIG = SimulationConfig()
R = CONFIG.radius_m
START = np.array([1.0, 0.6, 1.2])  # room_with_door: free space, the wall at x = 1.9


def flying_at(speed: float, other: np.ndarray | None) -> tuple[DroneSimulator, list]:
    """A drone in manual flight at ``speed`` along +x, 4 mm short of touching ``other``'s
    sphere (None: no other drone): the events of its next 0.2 s."""
    drone = DroneSimulator(CONFIG, room_with_door().flight_map)
    drone.spawn(START)
    drone.command_sticks((0.0, 0.0, speed / CONFIG.max_speed_m_s, 0.0))
    q = drone._modes.quad
    q.px, q.py, q.pz = START
    q.vx, q.vy, q.vz = speed, 0.0, 0.0
    if other is not None:
        drone.set_others(other[None])
    events = []
    while drone.time_s < 0.2:
        events += drone.advance(0.01)
    return drone, [e for e in events if e.kind != DroneEventKind.SPAWNED]


@pytest.mark.parametrize(
    "speed, kind", [(1.0, DroneEventKind.COLLISION), (2.5, DroneEventKind.CRASH)]
)
def test_a_drone_flying_into_another_bumps_or_crashes_as_into_a_wall(speed, kind):
    other = START + [2 * R + 0.004, 0.0, 0.0]
    drone, events = flying_at(speed, other)
    assert [e.kind for e in events][:1] == [kind], events
    q = drone._modes.quad
    # It never went into the other's sphere: the two stay at least two radii apart.
    assert np.linalg.norm([q.px, q.py, q.pz] - other) >= 2 * R - 1e-3
    if kind == DroneEventKind.CRASH:
        assert drone.status().mode == DroneMode.CRASHED
    else:
        assert drone.status().damage > 0  # a bump costs damage points, as on a wall


def test_without_another_drone_the_same_flight_touches_nothing():
    _, events = flying_at(1.0, None)
    assert events == []
    # and a drone elsewhere in the room changes nothing either
    _, events = flying_at(1.0, START + [0.0, 2.0, 0.0])
    assert events == []


def test_the_field_with_drones_is_the_maps_away_from_them_and_the_spheres_near_them():
    flight_map = room_with_door().flight_map
    centre = START + [0.7, 0.0, 0.0]
    field = WithDrones(flight_map, centre[None], R)
    far = START - [0.3, 0.0, 0.0]
    assert field.distance_at(*far) == pytest.approx(flight_map.distance_at(*far))
    near = centre - [R + 0.05, 0.0, 0.0]
    assert field.distance_at(*near) == pytest.approx(0.05)
    assert field.distance(near[None])[0] == pytest.approx(0.05)
    np.testing.assert_allclose(field.gradient(near[None])[0], [-1.0, 0.0, 0.0], atol=1e-9)
    through = np.array([START]), np.array([START + [0.6, 0.0, 0.0]])
    assert flight_map.segments_free(*through, R)[0] and not field.segments_free(*through, R)[0]
    beside = np.array([START + [0, 0.5, 0]]), np.array([START + [0.6, 0.5, 0.0]])
    assert field.segments_free(*beside, R)[0]


def test_other_drones_are_carried_on_at_their_velocity_for_a_while():
    others = OtherDrones(R)
    others.set([[1.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]], heard_s=10.0)
    np.testing.assert_allclose(others.at(10.1), [[1.1, 0.0, 1.0]])
    np.testing.assert_allclose(others.at(20.0), [[1.0 + CARRY_ON_S, 0.0, 1.0]])
    assert len(others) == 1


def test_a_drone_appears_clear_of_the_rooms_other_drones():
    """Two phones of a room often stand side by side: the second drone spawns (or a race
    restarts it) where the first hovers. It appears at the nearest free point clear of it."""
    flight_map = room_with_door().flight_map
    alone = DroneSimulator(CONFIG, flight_map)
    assert np.allclose(alone.spawn(START), START)  # free: where it was asked to
    drone = DroneSimulator(CONFIG, flight_map)
    drone.set_others(START[None])
    at = drone.spawn(START)
    gap = np.linalg.norm(at - START)
    assert R + CONFIG.planning_radius_m <= gap <= R + CONFIG.planning_radius_m + 0.1, at
    assert flight_map.distance(at[None])[0] >= CONFIG.planning_radius_m
    back = drone.put_back(START, 0.0, "a restart")
    assert np.linalg.norm(back - START) >= R + CONFIG.planning_radius_m, back
    # Drones all around it: no point within reach is clear of them: refused, as a full map.
    steps = np.arange(-4, 5) * 0.3  # 0.3 m apart: no point between them is 0.32 m clear
    swarm = START + np.stack(np.meshgrid(steps, steps, steps), axis=-1).reshape(-1, 3)
    crowded = DroneSimulator(CONFIG, flight_map)
    crowded.set_others(swarm)
    with pytest.raises(DroneCommandError, match="no observed free space"):
        crowded.spawn(START)
