"""The per-session drone simulator in synthetic scenes (server.simulation.scenes): spawn, hover,
goto with the real planner, manual flight, collisions, replanning, landing. Simulated faster
than real time by calling advance() in a loop; tolerances are stated in each test."""

from __future__ import annotations

import math
import threading

import numpy as np
import pytest

from server.simulation.config import SimulationConfig
from server.simulation.drone import DroneSimulator
from server.simulation.drone_types import DroneCommandError, DroneEventKind, DroneMode
from server.simulation.flight_map import FlightMap
from server.simulation.polyline import distances_to_segment, simplify
from server.simulation.route import PlanningError
from server.simulation.route_following import ROUTE_TOLERANCE_M
from server.simulation.scenes import Scene, box_in_the_way, corridor, room_with_door, sealed_room

CONFIG = SimulationConfig()
R = CONFIG.radius_m
FULL_PITCH = (0.0, 0.0, 1.0, 0.0)
CENTRED = (0.0, 0.0, 0.0, 0.0)


def spawned(scene, at=None, yaw=0.0) -> DroneSimulator:
    drone = DroneSimulator(CONFIG, scene.flight_map)
    drone.spawn(scene.start if at is None else np.asarray(at, float), yaw_rad=yaw)
    return drone


def fly(drone, seconds, dt=0.05, on_step=None):
    """Advance ``seconds`` in ``dt`` slices; returns events, positions (one per slice)."""
    events, positions = [], []
    for _ in range(round(seconds / dt)):
        events += drone.advance(dt)
        positions.append(drone.status().T_flight_drone[:3, 3])
        if on_step is not None:
            on_step(drone)
    return events, np.array(positions)


def kinds(events):
    return [e.kind for e in events]


def fly_until_arrived(drone, max_s, scene):
    """Fly until ``arrived`` (or max_s); returns events and the smallest clearances seen, per
    the flight map and per the scene's exact boxes, checked at every physics step."""
    events, worst_map, worst_true = [], np.inf, np.inf
    for _ in range(round(max_s * CONFIG.physics_hz / 4)):
        events += drone.advance(4 * CONFIG.dt_s)
        p = drone.status().T_flight_drone[:3, 3]
        worst_map = min(worst_map, float(scene.flight_map.distance(p[None])[0]))
        worst_true = min(worst_true, float(scene.true_distance(p[None])[0]))
        if DroneEventKind.ARRIVED in kinds(events):
            break
    return events, worst_map, worst_true


def test_spawn_hovers_near_the_camera_and_holds_within_5_mm():
    scene = room_with_door()
    drone = DroneSimulator(CONFIG, scene.flight_map)
    position = drone.spawn(scene.start)
    np.testing.assert_allclose(position, scene.start)  # free there: spawned right at it
    events, track = fly(drone, 5.0)
    assert kinds(events) == [DroneEventKind.SPAWNED]
    assert events[0].time_s == 0.0
    assert np.abs(track - scene.start).max() < 0.005
    status = drone.status()
    assert status.mode == DroneMode.HOVER and status.mode.value == "hover"
    assert status.time_s == pytest.approx(5.0)
    assert status.clearance == pytest.approx(0.6, abs=0.01)  # 0.6 m to the nearest wall
    assert status.route is None and status.target is None


def test_spawn_inside_a_wall_moves_to_free_space_or_refuses():
    scene = room_with_door()
    drone = DroneSimulator(CONFIG, scene.flight_map)
    position = drone.spawn([2.0, 0.5, 1.2])  # inside the dividing wall
    assert scene.flight_map.distance(position[None])[0] >= CONFIG.planning_radius_m
    assert np.linalg.norm(position - [2.0, 0.5, 1.2]) <= CONFIG.spawn_search_m
    with pytest.raises(DroneCommandError, match="no observed free space"):
        drone.spawn([20.0, 20.0, 20.0])  # far outside the map


def test_commands_before_spawn_are_refused():
    drone = DroneSimulator(CONFIG, room_with_door().flight_map)
    assert drone.advance(1.0) == []
    with pytest.raises(DroneCommandError, match="no drone yet"):
        drone.command_sticks(FULL_PITCH)
    with pytest.raises(DroneCommandError, match="no drone yet"):
        drone.status()


def test_advance_runs_whole_physics_steps_and_carries_the_rest():
    drone = spawned(room_with_door())
    for _ in range(3):
        drone.advance(0.001)  # 3 ms = 1 step of 2.5 ms, 0.5 ms left over
    assert drone.time_s == pytest.approx(CONFIG.dt_s)
    drone.advance(0.002)  # 0.5 + 2 ms = one more step
    assert drone.time_s == pytest.approx(2 * CONFIG.dt_s)


def test_goto_through_the_door_arrives_within_tolerance_in_8_s():
    scene = room_with_door()
    drone = spawned(scene)
    drone.command_goto(scene.goal, command_id=7)
    status = drone.status()
    assert status.mode == DroneMode.GOTO and status.command_id == 7
    np.testing.assert_allclose(status.target, scene.goal)
    assert 2 <= len(status.route) <= CONFIG.max_route_points
    events, worst_map, _ = fly_until_arrived(drone, 8.0, scene)  # a 2.8 m route at 1 m/s
    assert DroneEventKind.ARRIVED in kinds(events)
    assert DroneEventKind.COLLISION not in kinds(events)
    arrived = next(e for e in events if e.kind == DroneEventKind.ARRIVED)
    assert arrived.command_id == 7
    assert np.linalg.norm(arrived.position - scene.goal) <= CONFIG.arrival_tolerance_m
    assert worst_map >= R
    fly(drone, 1.0)
    status = drone.status()
    assert status.mode == DroneMode.HOVER
    assert np.linalg.norm(status.T_flight_drone[:3, 3] - scene.goal) < 0.02  # then holds it


@pytest.mark.parametrize("make_scene", [box_in_the_way, corridor])
def test_goto_around_obstacles_keeps_clearance_and_arrives(make_scene):
    scene = make_scene()
    drone = spawned(scene)
    drone.command_goto(scene.goal, speed=1.5)
    events, worst_map, worst_true = fly_until_arrived(drone, 15.0, scene)
    assert DroneEventKind.ARRIVED in kinds(events)
    assert DroneEventKind.COLLISION not in kinds(events)
    assert worst_map >= R
    assert worst_true >= R - CONFIG.voxel_m / 2  # against the exact box, not the grid


def test_unreachable_target_raises_and_the_drone_keeps_hovering():
    scene = sealed_room()
    drone = spawned(scene)
    fly(drone, 0.5)
    with pytest.raises(PlanningError) as info:
        drone.command_goto(scene.goal)
    assert info.value.reason in {"goal_blocked", "unreachable"}
    status = drone.status()
    assert status.mode == DroneMode.HOVER
    _, track = fly(drone, 2.0)
    assert np.abs(track - scene.start).max() < 0.005


def test_pushing_into_a_wall_below_crash_speed_bumps_and_stops_on_the_near_side():
    scene = room_with_door()  # wall face at x = 1.9 for y < 1.2
    drone = spawned(scene)
    wall_x = 1.9
    push = (0.0, 0.0, 0.35, 0.0)  # 1.05 m/s forward: below crash_speed_m_s (test_crash.py)
    xs, events = [], []
    for i in range(round(4.0 * CONFIG.physics_hz)):  # 4 s, one physics step per advance
        if i % (CONFIG.physics_hz // 10) == 0:
            drone.command_sticks(push)  # sticks at 10 Hz, forward (+x)
        events += drone.advance(CONFIG.dt_s)
        xs.append(drone.status().T_flight_drone[0, 3])
    xs = np.array(xs)
    collisions = kinds(events).count(DroneEventKind.COLLISION)
    assert 1 <= collisions <= 4  # pushing on: bumped again and again, reported once a second
    assert DroneEventKind.CRASH not in kinds(events)
    hit = next(e for e in events if e.kind == DroneEventKind.COLLISION)
    assert wall_x - R - 0.05 < hit.position[0] <= wall_x - R
    assert xs.max() <= wall_x - R + 1e-9  # the sphere never entered the wall, at any step
    drone.command_sticks(CENTRED)
    fly(drone, 2.0)
    status = drone.status()
    assert np.linalg.norm(status.velocity) < 0.02  # stopped
    assert status.T_flight_drone[0, 3] <= wall_x - R + 1e-6
    assert status.mode == DroneMode.MANUAL and status.damage > 0


@pytest.mark.parametrize(
    "sticks, contact",
    [
        ((0.1, 0.0, 0.4, 0.3), DroneEventKind.COLLISION),
        ((0.1, 0.0, 1.0, 0.3), DroneEventKind.CRASH),
    ],
    ids=["bump", "crash"],
)
def test_checking_steps_in_chunks_rewinds_to_exactly_the_stepwise_result(sticks, contact):
    scene = room_with_door()
    runs = []
    for per_call in (1, 40):  # one physics step per advance, or 0.1 s (chunks near the wall)
        drone = spawned(scene, at=(1.3, 0.6, 1.2))
        events = []
        for _ in range(round(1.5 * CONFIG.physics_hz / per_call)):
            if round(drone.time_s / CONFIG.dt_s) % 40 == 0:
                drone.command_sticks(sticks)
            events += drone.advance(per_call * CONFIG.dt_s)
        runs.append((events, drone.status()))
    (events_a, status_a), (events_b, status_b) = runs
    assert contact in kinds(events_a)
    assert [(e.kind, e.time_s) for e in events_a] == [(e.kind, e.time_s) for e in events_b]
    for a, b in zip(events_a, events_b, strict=True):
        np.testing.assert_array_equal(a.position, b.position)
    np.testing.assert_array_equal(status_a.T_flight_drone, status_b.T_flight_drone)
    np.testing.assert_array_equal(status_a.velocity, status_b.velocity)
    assert status_a.damage == status_b.damage


def test_manual_flight_follows_the_sticks_then_centred_sticks_hold_position():
    scene = room_with_door()
    drone = spawned(scene, yaw=math.pi / 2)  # facing +y
    for _ in range(10):  # 1 s of half pitch and a little right roll, at 10 Hz
        drone.command_sticks((0.3, 0.0, 0.5, 0.2))
        drone.advance(0.1)
    status = drone.status()
    assert status.mode == DroneMode.MANUAL
    v = status.velocity
    assert v[1] > 0.5 * 0.5 * CONFIG.max_speed_m_s  # forward is +y
    assert v[0] > 0.1  # right of +y is +x
    assert v[2] > 0.1  # climbing
    drone.command_sticks(CENTRED)
    fly(drone, 2.0)
    held = drone.status().T_flight_drone[:3, 3]
    drone.command_sticks(CENTRED)
    _, track = fly(drone, 3.0, on_step=lambda d: d.command_sticks(CENTRED))
    assert drone.status().mode == DroneMode.MANUAL
    assert np.abs(track - held).max() < 0.01


def test_yaw_stick_turns_counter_clockwise():
    drone = spawned(room_with_door())
    for _ in range(5):
        drone.command_sticks((0.0, 0.5, 0.0, 0.0))
        drone.advance(0.1)
    R_fd = drone.status().T_flight_drone[:3, :3]
    yaw = math.atan2(R_fd[1, 0], R_fd[0, 0])
    expected = 0.5 * math.radians(CONFIG.max_yaw_rate_deg_s) * 0.5
    assert yaw == pytest.approx(expected, abs=math.radians(5))


def test_stale_sticks_count_as_centred():
    scene = room_with_door()
    fresh, stale = spawned(scene, yaw=math.pi / 2), spawned(scene, yaw=math.pi / 2)
    forward = (0.0, 0.0, 0.4, 0.0)  # along +y, where the room is 2.4 m deep
    for _ in range(15):  # 1.5 s; only `fresh` gets its sticks repeated
        fresh.command_sticks(forward)
        fresh.advance(0.1)
    stale.command_sticks(forward)
    stale.advance(1.5)
    assert fresh.status().velocity[1] > 0.3 * CONFIG.max_speed_m_s
    assert abs(stale.status().velocity[1]) < 0.15  # stick timed out after 0.5 s: braked
    # Sticks read long ago are centred from the start.
    old = spawned(scene)
    fly(old, 1.0)
    old.command_sticks(FULL_PITCH, now_s=old.time_s - 2 * CONFIG.stick_timeout_s)
    _, track = fly(old, 1.0)
    assert np.abs(track - scene.start).max() < 0.005


def test_an_obstacle_on_the_route_triggers_a_replan_and_the_drone_still_arrives():
    walls = [
        ((-0.1, -0.1, -0.1), (5.1, 3.1, 0.0)),
        ((-0.1, -0.1, 2.4), (5.1, 3.1, 2.5)),
        ((-0.1, -0.1, 0.0), (0.0, 3.1, 2.4)),
        ((5.0, -0.1, 0.0), (5.1, 3.1, 2.4)),
        ((0.0, -0.1, 0.0), (5.0, 0.0, 2.4)),
        ((0.0, 3.0, 0.0), (5.0, 3.1, 2.4)),
    ]
    lo, hi = (-0.1, -0.1, -0.1), (5.1, 3.1, 2.5)
    flight_map = FlightMap.from_boxes(lo, hi, walls, CONFIG.voxel_m)
    start, goal = np.array([0.8, 1.5, 1.2]), np.array([4.2, 1.5, 1.2])
    drone = DroneSimulator(CONFIG, flight_map)
    drone.spawn(start)
    drone.command_goto(goal)
    assert np.abs(drone.status().route[:, 1] - 1.5).max() < 0.05  # straight down the room
    events, _ = fly(drone, 1.0)
    assert drone.status().T_flight_drone[0, 3] < 2.0  # not at the obstacle yet

    obstacle = ((2.6, 0.0, 0.0), (2.9, 2.2, 2.4))  # a wall across, gap at y > 2.2
    grown = FlightMap.from_boxes(lo, hi, walls + [obstacle], CONFIG.voxel_m)
    changed = flight_map.update(grown.origin, grown.blocked, np.ones(grown.shape, bool))
    drone.on_map_update(changed)
    events += drone.advance(0.0)
    assert DroneEventKind.REPLANNED in kinds(events)
    assert drone.status().route[:, 1].max() > 2.2  # through the gap

    boxes = [(np.array(a), np.array(b)) for a, b in walls + [obstacle]]
    scene = Scene("replan", flight_map, boxes, start, goal)  # exact distances for the helper
    more, worst_map, worst_true = fly_until_arrived(drone, 20.0, scene)
    assert DroneEventKind.ARRIVED in kinds(more)
    assert DroneEventKind.COLLISION not in kinds(events + more)
    assert worst_map >= R and worst_true >= R - CONFIG.voxel_m / 2


def test_a_route_blocked_for_good_emits_blocked_and_holds():
    scene = box_in_the_way()
    drone = spawned(scene)
    drone.command_goto(scene.goal)
    fly(drone, 0.5)
    fm = scene.flight_map
    sealed = fm.blocked.copy()
    i = int((3.5 - fm.origin[0]) / fm.voxel_m)
    sealed[i : i + 3] = True  # a full wall across the room at x = 3.5
    assert drone.update_map(fm.origin, sealed, np.ones(fm.shape, bool)) is not None
    events, _ = fly(drone, 2.0)
    assert DroneEventKind.BLOCKED in kinds(events)
    # Its text names the goal only through the frame the reader asks for (the session's world
    # frame is not the simulator's), never in the simulator's own coordinates.
    blocked = next(e for e in events if e.kind == DroneEventKind.BLOCKED)
    np.testing.assert_allclose(blocked.point, scene.goal)
    shifted = blocked.text(lambda p: p + 10.0)
    assert "({:.2f}, {:.2f}, {:.2f}) m".format(*(scene.goal + 10.0)) in shifted, shifted
    assert "({:.2f}, {:.2f}, {:.2f}) m".format(*scene.goal) not in shifted
    assert drone.status().mode == DroneMode.HOVER
    assert drone.status().T_flight_drone[0, 3] < 3.5 - R


def test_hold_during_goto_stops_and_hovers():
    scene = box_in_the_way()
    drone = spawned(scene)
    drone.command_goto(scene.goal)
    fly(drone, 1.0)
    drone.command_hold(command_id=3)
    fly(drone, 2.0)
    held = drone.status().T_flight_drone[:3, 3]
    _, track = fly(drone, 2.0)
    status = drone.status()
    assert status.mode == DroneMode.HOVER and status.command_id == 3
    assert status.route is None
    assert np.abs(track - held).max() < 0.005


def test_land_touches_down_and_takeoff_rises_again():
    scene = room_with_door()
    drone = spawned(scene)
    drone.command_land(command_id=4)
    assert drone.status().mode == DroneMode.LANDING
    events, _ = fly(drone, 5.0)
    assert kinds(events) == [DroneEventKind.SPAWNED, DroneEventKind.LANDED]
    landed = events[-1]
    assert landed.command_id == 4
    status = drone.status()
    assert status.mode == DroneMode.LANDED
    assert R <= status.T_flight_drone[2, 3] < R + 0.03  # resting on the floor (z = 0)
    np.testing.assert_allclose(status.T_flight_drone[:2, 3], scene.start[:2], atol=0.01)
    assert np.all(status.velocity == 0)
    with pytest.raises(DroneCommandError, match="landed"):
        drone.command_goto(scene.goal)
    drone.command_takeoff()
    fly(drone, 4.0)
    status = drone.status()
    assert status.mode == DroneMode.HOVER
    assert status.T_flight_drone[2, 3] == pytest.approx(landed.position[2] + 1.0, abs=0.02)


def test_throttle_up_when_landed_takes_off_into_manual_flight():
    drone = spawned(room_with_door())
    drone.command_land()
    fly(drone, 4.0)
    z0 = drone.status().T_flight_drone[2, 3]
    drone.command_sticks((0.3, 0.0, 0.0, 0.0))  # below half throttle: stays on the ground
    fly(drone, 0.3)
    assert drone.mode == DroneMode.LANDED
    for _ in range(5):
        drone.command_sticks((1.0, 0.0, 0.0, 0.0))
        drone.advance(0.1)
    assert drone.mode == DroneMode.MANUAL
    assert drone.status().T_flight_drone[2, 3] > z0 + 0.2
    assert drone.status().velocity[2] > 0.5 * CONFIG.max_climb_rate_m_s


def test_goto_with_a_bad_target_is_refused_and_changes_nothing():
    scene = room_with_door()
    drone = spawned(scene)
    for bad in ([1.0, float("nan"), 1.0], [1.0, 2.0]):
        with pytest.raises(DroneCommandError, match="goto target"):
            drone.command_goto(bad)
    with pytest.raises(PlanningError) as info:
        drone.command_goto([2.0, 0.5, 1.2])  # inside the wall
    assert info.value.reason == "goal_blocked"
    assert info.value.nearest is not None
    assert scene.flight_map.distance(info.value.nearest[None])[0] >= R
    assert drone.status().mode == DroneMode.HOVER


def test_takeoff_under_a_low_ceiling_stops_below_it():
    scene = box_in_the_way()  # box top at z = 1.8, a free layer of 0.6 m above it
    drone = spawned(scene, at=(2.5, 1.5, 2.1))
    drone.command_land()
    fly(drone, 3.0)
    assert drone.mode == DroneMode.LANDED
    z0 = drone.status().T_flight_drone[2, 3]
    assert 1.8 + R <= z0 < 1.8 + R + 0.03  # on the box
    drone.command_takeoff()
    fly(drone, 3.0)
    z = drone.status().T_flight_drone[2, 3]
    assert z0 + 0.1 < z <= 2.4 - CONFIG.planning_radius_m + 0.01  # below the ceiling
    assert drone.status().clearance >= CONFIG.planning_radius_m - 0.01


def test_commands_from_another_thread_while_advancing():
    scene = room_with_door()
    drone = spawned(scene)
    stop = threading.Event()
    errors = []

    def pilot():
        try:
            while not stop.is_set():
                drone.command_sticks((0.0, 0.2, 0.0, 0.0))
                drone.status()
        except Exception as exc:  # pragma: no cover - reported below
            errors.append(exc)

    thread = threading.Thread(target=pilot)
    thread.start()
    try:
        fly(drone, 1.0, dt=0.01)
    finally:
        stop.set()
        thread.join()
    assert not errors
    assert drone.status().mode == DroneMode.MANUAL
    assert drone.status().clearance >= R


def test_status_route_is_the_corners_of_the_path_ahead():
    """drone_state carries the route's corners: the setpoint first, then vertices that a client
    joins with straight lines staying within ROUTE_TOLERANCE_M of the path still ahead."""
    scene = room_with_door()
    drone = spawned(scene)
    drone.command_goto(scene.goal)
    for _ in range(6):
        route = drone.status().route
        tracker = drone._modes.follower.tracker
        dense = tracker.remaining(drone._modes.setpoint())
        assert len(route) < len(dense) / 5  # corners, not samples
        np.testing.assert_allclose(route[0], dense[0])  # where the drone is headed now
        np.testing.assert_allclose(route[-1], scene.goal, atol=1e-9)
        # Every path sample ahead is within the tolerance of the drawn polyline.
        gaps = np.min(
            [distances_to_segment(dense, a, b) for a, b in zip(route[:-1], route[1:], strict=True)],
            axis=0,
        )
        assert gaps.max() <= ROUTE_TOLERANCE_M + 1e-9
        fly(drone, 0.5)


def test_douglas_peucker_keeps_the_corners_within_the_tolerance():
    t = np.linspace(0, 1, 201)[:, None]
    corner = np.vstack([t * [1.0, 0, 0], [1.0, 0, 0] + t[1:] * [0, 1.0, 0]])  # an L
    np.testing.assert_array_equal(simplify(corner, 0.01), [0, 200, 400])
    arc = np.stack([np.cos(t[:, 0] * np.pi), np.sin(t[:, 0] * np.pi), 0 * t[:, 0]], axis=1)
    keep = simplify(arc, 0.02)
    assert 5 < len(keep) < 40 and keep[0] == 0 and keep[-1] == 200
    for a, b in zip(keep[:-1], keep[1:], strict=True):
        assert distances_to_segment(arc[a : b + 1], arc[a], arc[b]).max() <= 0.02
