"""Skipping the physics of a drone that holds still (server.simulation.stillness): the same
flight as stepping every step, to the bit while the drone rests where it spawned, within a
nanometre once it has settled after a flight; and it wakes on every command and map change.

Each test flies two simulators side by side, one skipping (the default) and one stepping every
step (``skip_still=False``), through the same script, and compares them after every slice."""

from __future__ import annotations

import numpy as np

from server.simulation.config import SimulationConfig
from server.simulation.drone import DroneSimulator
from server.simulation.drone_types import DroneEventKind, DroneMode
from server.simulation.scenes import room_with_door
from server.simulation.stillness import SETTLED

CONFIG = SimulationConfig()
SLICE_S = 0.05  # the flight thread's step at drone_state_hz 20
CENTRED = (0.0, 0.0, 0.0, 0.0)
# A settled drone differs from the stepping one by what settling moved it (SETTLED, 1e-9 in
# SI units), then by what the controller makes of that: 10 nm, 10 nm/s, ... at most.
NEAR = 1e-8
assert SETTLED < NEAR


def pair(at=None, yaw=0.0):
    """(skipping, stepping) drones spawned at the same place in their own copy of the door
    room (a map change then changes one drone's map only)."""
    drones = []
    for skip in (True, False):
        scene = room_with_door(CONFIG.voxel_m)
        drone = DroneSimulator(CONFIG, scene.flight_map, skip_still=skip)
        drone.spawn(scene.start if at is None else at, yaw_rad=yaw)
        drones.append(drone)
    return drones[0], drones[1], scene


def record(drone: DroneSimulator, events) -> tuple:
    s = drone.status()
    q = drone._modes.quad
    return (
        s.time_s,
        s.mode,
        q.state(),
        tuple((e.kind, e.time_s, tuple(e.position)) for e in events),
    )


def fly_both(skipping, stepping, seconds, command=None, tol=0.0):
    """Advance both ``seconds`` in slices, ``command(drone, i)`` before slice i; asserts the
    same times, modes and events after every slice and states equal within ``tol`` (0: to the
    bit). Returns how many steps the skipping drone skipped."""
    skipped = skipping.stillness.skipped
    for i in range(round(seconds / SLICE_S)):
        if command is not None:
            command(skipping, i)
            command(stepping, i)
        a = record(skipping, skipping.advance(SLICE_S))
        b = record(stepping, stepping.advance(SLICE_S))
        if tol == 0.0:
            assert a == b, f"slice {i}: {a} != {b}"
        else:
            assert (a[0], a[1]) == (b[0], b[1]), f"slice {i}"
            assert [e[0] for e in a[3]] == [e[0] for e in b[3]], f"slice {i}"
            np.testing.assert_allclose(a[2], b[2], rtol=0, atol=tol, err_msg=f"slice {i}")
    assert stepping.stillness.skipped == 0
    return skipping.stillness.skipped - skipped


def test_a_drone_resting_where_it_spawned_skips_its_steps_and_flies_on_the_same():
    skipping, stepping, scene = pair(yaw=2.9)
    # At rest after the spawn: a fixed point from the first step, nothing to settle.
    assert fly_both(skipping, stepping, 2.0) >= 0.9 * 2.0 * CONFIG.physics_hz
    assert skipping.stillness.still
    # A goto wakes it: the route flown is the stepping drone's, to the bit.
    skipping.command_goto(scene.goal, speed=2.0)
    stepping.command_goto(scene.goal, speed=2.0)
    assert not fly_both(skipping, stepping, 1.0)
    assert not skipping.stillness.still
    assert skipping.mode == DroneMode.GOTO


def test_after_a_flight_the_settled_drone_stays_within_a_nanometre_of_stepping():
    skipping, stepping, scene = pair()
    for drone in (skipping, stepping):
        drone.command_goto(scene.goal, speed=2.0)
    # Arrives, then creeps towards its fixed point until it is settled onto it (~8 s).
    assert fly_both(skipping, stepping, 20.0, tol=NEAR) > 0
    assert skipping.stillness.still
    q = skipping._modes.quad
    assert (q.vx, q.vy, q.vz, q.wx, q.wy, q.wz) == (0.0,) * 6
    np.testing.assert_array_equal(q.position, scene.goal)  # exactly at the held point
    # The flight back and the landing are the stepping drone's, within a nanometre or so.
    for drone in (skipping, stepping):
        drone.command_goto(scene.start, speed=1.5)
    assert not fly_both(skipping, stepping, 6.0, tol=NEAR)
    for drone in (skipping, stepping):
        drone.command_land()
    fly_both(skipping, stepping, 4.0, tol=NEAR)
    assert skipping.mode == DroneMode.LANDED


def test_every_command_wakes_a_still_drone():
    skipping, stepping, scene = pair(at=np.array([1.0, 1.5, 1.2]))
    commands = [  # (command, whether the drone moves)
        (lambda d: d.command_sticks((0.3, 0.2, 0.4, -0.3)), True),  # manual, position mode
        (lambda d: d.command_hold(), False),  # hover where it holds: still again at once
        (lambda d: d.set_flight_mode("angle"), False),  # for the sticks; it hovers on
        (lambda d: d.command_sticks((0.0, 0.0, -0.15, 0.0)), True),  # angle mode: tilts back
        (lambda d: d.command_goto(scene.start), True),
        (lambda d: d.command_land(), True),
    ]
    fly_both(skipping, stepping, 1.0)
    for command, moves in commands:
        assert skipping.stillness.still
        before = skipping.status().T_flight_drone[:3, 3]
        command(skipping)
        command(stepping)
        fly_both(skipping, stepping, 12.0, tol=NEAR)
        after = skipping.status().T_flight_drone[:3, 3]
        assert np.linalg.norm(after - before) > (0.05 if moves else -1.0)
        assert skipping.stillness.still or skipping.mode == DroneMode.LANDED
    assert skipping.mode == DroneMode.LANDED


def test_sticks_sent_centred_keep_the_drone_still_in_position_mode_only():
    skipping, stepping, scene = pair()
    for drone in (skipping, stepping):
        drone.command_sticks((0.0, 0.0, 0.6, 0.0))  # fly forward, then let go
    fly_both(skipping, stepping, 1.0)

    def centred_at_15_hz(drone, i):
        if i % 4 == 0:  # as the page: every 67 ms while connected, centred too
            drone.command_sticks(CENTRED)

    # Position mode: braked, it holds, and holding it is still even with sticks coming in.
    assert fly_both(skipping, stepping, 15.0, centred_at_15_hz, tol=NEAR) > 0
    assert skipping.mode == DroneMode.MANUAL and skipping.stillness.still
    # Angle mode: fresh sticks fly the attitude controller (no position hold): never skipped
    # while they come.
    for drone in (skipping, stepping):
        drone.set_flight_mode("angle")
    assert not fly_both(skipping, stepping, 3.0, centred_at_15_hz, tol=NEAR)
    # Stale sticks hand it to position mode, which brakes and holds: still again.
    assert fly_both(skipping, stepping, 15.0, tol=NEAR) > 0
    assert skipping.stillness.still


def test_a_map_change_wakes_a_still_drone_it_grows_into():
    skipping, stepping, scene = pair()
    fly_both(skipping, stepping, 1.0)
    assert skipping.stillness.still
    # A map change away from the drone: it holds on, still (a drone that does not move touches
    # nothing), and stays the stepping drone.
    far = skipping.flight_map
    for drone in (skipping, stepping):
        fm = drone.flight_map
        occupied = fm.blocked.copy()
        occupied[2:4, 2:4, 2:4] = True
        drone.update_map(fm.origin, occupied, np.ones(fm.shape, dtype=bool))
    assert fly_both(skipping, stepping, 1.0) > 0
    # The map grows into the drone: it is moved out (a collision event) and flies on as the
    # stepping drone does.
    p = skipping.status().T_flight_drone[:3, 3]
    for drone in (skipping, stepping):
        fm = drone.flight_map
        occupied = fm.blocked.copy()
        i, j, k = np.floor((p - fm.origin) / fm.voxel_m).astype(int)
        occupied[i - 1 : i + 2, j - 1 : j + 2, k - 1 : k + 2] = True
        drone.update_map(fm.origin, occupied, np.ones(fm.shape, dtype=bool))
        events = drone.advance(SLICE_S)
        assert DroneEventKind.COLLISION in [e.kind for e in events]
    assert far is skipping.flight_map
    assert not np.array_equal(skipping.status().T_flight_drone[:3, 3], p)
    fly_both(skipping, stepping, 3.0)


def test_a_corrected_world_wakes_a_still_drone():
    skipping, stepping, scene = pair()
    fly_both(skipping, stepping, 1.0)
    assert skipping.stillness.still
    yaw = 0.1
    T = np.eye(4)
    T[:3, :3] = [[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]]
    T[:3, 3] = [0.02, -0.01, 0.0]
    for drone in (skipping, stepping):
        fm = drone.flight_map
        drone.move_with_world(T, fm.origin, fm.blocked, np.ones(fm.shape, dtype=bool))
    moved = skipping.status().T_flight_drone[:3, 3]
    np.testing.assert_allclose(moved, T[:3, :3] @ scene.start + T[:3, 3], atol=1e-12)
    fly_both(skipping, stepping, 2.0, tol=NEAR)
    assert skipping.stillness.still


def test_any_change_of_its_state_ends_the_skipping():
    """No wake-up call to forget: whatever changes what a step reads (here a gust kicking the
    drone, then its held point moved, done to both drones alike) ends the skipping at the next
    advance, and the drone flies as the stepping one, to the bit."""
    skipping, stepping, scene = pair()
    fly_both(skipping, stepping, 1.0)
    assert skipping.stillness.still
    for drone in (skipping, stepping):
        drone._modes.quad.vx = 0.5
    assert not fly_both(skipping, stepping, 1.0)
    assert skipping.status().T_flight_drone[0, 3] > scene.start[0] + 0.01  # pushed on
    fly_both(skipping, stepping, 12.0, tol=NEAR)
    assert skipping.stillness.still
    for drone in (skipping, stepping):
        drone._modes.sp.x -= 0.3
    assert not fly_both(skipping, stepping, 1.0, tol=NEAR)
    assert not skipping.stillness.still
