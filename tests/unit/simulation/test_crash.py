"""Crashes and bumps (server.simulation.drone): a contact at crash_speed_m_s or faster along the
surface normal is a crash (motors off, the drone falls and lands, the pilot takes off again);
below it a bump (bounce, damage points). The drone as drawn matches its collision sphere."""

from __future__ import annotations

import re
from dataclasses import replace

import numpy as np
import pytest

from server.errors import ConfigError
from server.simulation.config import SimulationConfig
from server.simulation.drone import DroneSimulator
from server.simulation.drone_types import DroneCommandError, DroneEventKind, DroneMode
from server.simulation.scenes import room_with_door
from tests.support.paths import REPO

CONFIG = SimulationConfig()
R = CONFIG.radius_m
WALL_X = 1.9  # room_with_door: the dividing wall's face for y < 1.2
FLOOR_Z = 0.0


def at_the_wall(velocity, config: SimulationConfig = CONFIG, gap_m: float = 0.004):
    """A drone in manual flight ``gap_m`` from the wall's face, moving at ``velocity`` (flight
    frame, m/s), its sticks holding that velocity: it touches within a step or two, at that
    speed (the controller has no time to change it)."""
    scene = room_with_door()
    drone = DroneSimulator(config, scene.flight_map)
    drone.spawn([1.5, 0.6, 1.2])
    v = np.asarray(velocity, float)
    drone.command_sticks((0.0, 0.0, v[0] / config.max_speed_m_s, -v[1] / config.max_speed_m_s))
    q = drone._modes.quad  # as if it had flown in at this speed, to there
    q.px, q.py, q.pz = WALL_X - R - gap_m, 0.6, 1.2
    q.vx, q.vy, q.vz = v
    return drone


def advance_until(drone, kinds, max_s=5.0, dt=0.01):
    events = []
    while drone.time_s < max_s and not any(e.kind in kinds for e in events):
        events += drone.advance(dt)
    return events


@pytest.mark.parametrize("speed, crash", [(1.3, False), (1.45, False), (1.55, True), (2.5, True)])
def test_the_normal_speed_into_the_map_decides_crash_or_bump(speed, crash):
    drone = at_the_wall([speed, 0.0, 0.0])
    events = advance_until(drone, {DroneEventKind.COLLISION, DroneEventKind.CRASH}, max_s=0.2)
    (contact,) = [e for e in events if e.kind != DroneEventKind.SPAWNED]
    said = float(re.search(r"at (\d+\.\d+) m/s", contact.message).group(1))
    assert said == pytest.approx(speed, abs=0.03)  # the message gives the normal speed
    status = drone.status()
    if crash:
        assert contact.kind == DroneEventKind.CRASH
        assert status.mode == DroneMode.CRASHED and status.damage == 0.0
        assert "take off again" in contact.message
    else:
        assert contact.kind == DroneEventKind.COLLISION and "bumped" in contact.message
        assert status.mode == DroneMode.MANUAL
        assert status.velocity[0] < 0  # bounced back
        # Reflected with bump_restitution of the normal speed (the controller is already
        # pulling it on, hence the tolerance), damage by bump_damage_per_m_s.
        assert -status.velocity[0] == pytest.approx(CONFIG.bump_restitution * speed, abs=0.06)
        assert status.damage == pytest.approx(CONFIG.bump_damage_per_m_s * said, abs=0.2)
    assert status.T_flight_drone[0, 3] <= WALL_X - R + 1e-9  # never inside the wall


def test_a_grazing_contact_is_judged_by_its_normal_speed_not_its_total_speed():
    drone = at_the_wall([0.5, -2.5, 0.0])  # 2.55 m/s in all, 0.5 m/s into the wall
    events = advance_until(drone, {DroneEventKind.COLLISION, DroneEventKind.CRASH}, max_s=0.2)
    assert DroneEventKind.COLLISION in [e.kind for e in events]
    assert DroneEventKind.CRASH not in [e.kind for e in events]
    status = drone.status()
    assert status.mode == DroneMode.MANUAL
    # Along the wall it keeps (1 - bump_friction) of its speed: damped, not stopped.
    assert status.velocity[1] == pytest.approx(-2.5 * (1 - CONFIG.bump_friction), abs=0.15)


def test_a_crashed_drone_falls_lands_and_must_take_off_again():
    drone = at_the_wall([2.5, 0.0, 0.0])
    events = advance_until(drone, {DroneEventKind.CRASH}, max_s=0.2)
    assert drone.status().mode == DroneMode.CRASHED
    # While it falls: no command flies it; sticks are ignored, land changes nothing.
    for command in (lambda: drone.command_goto([1.0, 1.0, 1.2]), drone.command_hold):
        with pytest.raises(DroneCommandError, match="crashed"):
            command()
    with pytest.raises(DroneCommandError, match="landed drone"):
        drone.command_takeoff()
    drone.command_sticks((1.0, 0.0, 1.0, 0.0))
    drone.command_land()
    heights = []
    while drone.status().mode == DroneMode.CRASHED and drone.time_s < 5:
        events += drone.advance(0.01)
        heights.append(drone.status().T_flight_drone[2, 3])
    status = drone.status()
    assert status.mode == DroneMode.LANDED
    assert [e.kind for e in events][-1] == DroneEventKind.LANDED
    assert np.all(np.diff(heights) <= 1e-9)  # straight down, never up again
    fall_s = status.time_s - next(e.time_s for e in events if e.kind == DroneEventKind.CRASH)
    assert 0.4 < fall_s < 1.0  # about sqrt(2 h / g) from 1.2 m, with a little drag
    z = status.T_flight_drone[2, 3]
    assert FLOOR_Z + R - 0.01 <= z <= FLOOR_Z + R + 0.05  # on the floor, its sphere resting
    assert status.T_flight_drone[2, 2] > 0.999  # level again
    assert np.linalg.norm(status.velocity) == 0.0
    # It stays down until the pilot takes off again.
    drone.advance(1.0)
    assert drone.status().mode == DroneMode.LANDED
    drone.command_takeoff()
    events = []
    for _ in range(60):
        events += drone.advance(0.05)
    status = drone.status()
    assert status.mode == DroneMode.HOVER and status.T_flight_drone[2, 3] > z + 0.8
    assert DroneEventKind.COLLISION not in [e.kind for e in events]


def test_crash_speed_and_bump_settings_are_checked():
    with pytest.raises(ConfigError, match="bump_restitution"):
        SimulationConfig(bump_restitution=1.0)
    with pytest.raises(ConfigError, match="crash_speed_m_s"):
        SimulationConfig(crash_speed_m_s=0.0)
    lenient = replace(CONFIG, crash_speed_m_s=10.0)
    drone = at_the_wall([2.5, 0.0, 0.0], lenient)
    events = advance_until(drone, {DroneEventKind.COLLISION, DroneEventKind.CRASH}, max_s=0.2)
    assert DroneEventKind.COLLISION in [e.kind for e in events]  # a bump at this setting


def test_the_drawn_drone_fits_inside_its_collision_sphere():
    """client_web/js/views/drone_model.js draws the airframe the simulator flies: its rotors' tips
    (arm length + rotor radius) reach the collision sphere's radius and no further."""
    source = (REPO / "client_web" / "js" / "views" / "drone_model.js").read_text()
    arm = float(re.search(r"const ARM_LENGTH = ([\d.]+)", source).group(1))
    rotor = float(re.search(r"const ROTOR_RADIUS = ([\d.]+)", source).group(1))
    assert arm == pytest.approx(CONFIG.arm_length_m)
    assert arm + rotor == pytest.approx(CONFIG.radius_m)
    body = [
        float(v)
        for v in re.search(r"BoxGeometry\(([\d., ]+)\), paint\)\); // body", source)
        .group(1)
        .split(",")
    ]
    assert np.hypot(body[0] / 2, body[1] / 2) < CONFIG.radius_m
    protocol = (REPO / "shared" / "PROTOCOL.md").read_text()
    assert "collision sphere" in protocol and f"{CONFIG.radius_m:.2f} m" in protocol
