"""Quadrotor dynamics and the cascaded controller, without a map: physics sanity, hover, steps,
limits. Everything runs faster than real time at the default 400 Hz."""

from __future__ import annotations

import math

import numpy as np
import pytest

from server.errors import ConfigError
from server.simulation.config import SimulationConfig
from server.simulation.control import CascadedController, ControlGains, ControlLimits, Setpoint
from server.simulation.quadrotor import Quadrotor, QuadrotorParams, mix

CONFIG = SimulationConfig()
PARAMS = QuadrotorParams.from_config(CONFIG)


def make_quad(position=(0.0, 0.0, 1.0), yaw=0.0) -> tuple[Quadrotor, CascadedController]:
    quad = Quadrotor(PARAMS, CONFIG.dt_s)
    quad.reset(position, yaw)
    ctrl = CascadedController(
        PARAMS, ControlGains.from_config(CONFIG), ControlLimits.from_config(CONFIG)
    )
    return quad, ctrl


def fly(quad, ctrl, sp, seconds):
    """Fly ``seconds`` under control; returns positions, speeds (horizontal), climb rates, tilts."""
    n = round(seconds * CONFIG.physics_hz)
    out = np.empty((n, 6))
    for i in range(n):
        quad.step(*ctrl.update(quad, sp))
        out[i] = (quad.px, quad.py, quad.pz, math.hypot(quad.vx, quad.vy), quad.vz, quad.tilt_rad)
    return out


def test_motors_off_free_fall_with_linear_drag():
    quad = Quadrotor(PARAMS, CONFIG.dt_s)
    quad.reset((0.0, 0.0, 10.0), hovering=False)
    t = 1.5
    for _ in range(round(t * CONFIG.physics_hz)):
        quad.step(0.0, 0.0, 0.0, 0.0)
    k = PARAMS.drag_n_s_m / PARAMS.mass_kg
    g = PARAMS.gravity_m_s2
    vz = -(g / k) * (1 - math.exp(-k * t))
    z = 10.0 - (g / k) * (t - (1 - math.exp(-k * t)) / k)
    assert quad.vz == pytest.approx(vz, abs=0.01)
    assert quad.pz == pytest.approx(z, abs=0.02)
    assert abs(quad.vz) < g * t  # drag slowed it down
    assert (quad.px, quad.py, quad.vx, quad.vy) == (0.0, 0.0, 0.0, 0.0)


def test_hover_thrust_balances_gravity_exactly():
    quad = Quadrotor(PARAMS, CONFIG.dt_s)
    quad.reset((1.0, 2.0, 3.0), yaw_rad=0.7)
    f = PARAMS.hover_thrust_n
    for _ in range(CONFIG.physics_hz * 5):
        quad.step(f, f, f, f)
    np.testing.assert_allclose(quad.position, [1.0, 2.0, 3.0], atol=1e-9)
    assert quad.yaw_rad == pytest.approx(0.7, abs=1e-12)


def test_motor_lag_is_first_order():
    quad = Quadrotor(PARAMS, CONFIG.dt_s)
    quad.reset((0.0, 0.0, 0.0), hovering=False)
    tau = PARAMS.motor_time_constant_s
    for _ in range(round(tau * CONFIG.physics_hz)):
        quad.step(2.0, 2.0, 2.0, 2.0)
    assert quad.f0 == pytest.approx(2.0 * (1 - math.exp(-1)), rel=1e-6)  # 63% after one tau


def test_mixer_reproduces_thrust_and_torques():
    f = mix(PARAMS, 6.0, 0.02, -0.03, 0.01)
    a = PARAMS.arm_length_m / math.sqrt(2)
    assert sum(f) == pytest.approx(6.0)
    assert a * (f[0] - f[1] - f[2] + f[3]) == pytest.approx(0.02)
    assert a * (-f[0] - f[1] + f[2] + f[3]) == pytest.approx(-0.03)
    assert PARAMS.yaw_moment_m * (f[0] - f[1] + f[2] - f[3]) == pytest.approx(0.01)


def test_mixer_gives_up_yaw_before_roll_when_saturated():
    a = PARAMS.arm_length_m / math.sqrt(2)
    f = mix(PARAMS, 4 * PARAMS.hover_thrust_n, 0.1, 0.0, 0.5)  # huge yaw demand
    assert all(0.0 <= fi <= PARAMS.max_motor_thrust_n for fi in f)
    assert a * (f[0] - f[1] - f[2] + f[3]) == pytest.approx(0.1)  # roll kept in full
    assert sum(f) == pytest.approx(4 * PARAMS.hover_thrust_n)


def test_left_motors_roll_right_side_down_and_attitude_stays_orthonormal():
    quad = Quadrotor(PARAMS, CONFIG.dt_s)
    quad.reset((0.0, 0.0, 0.0))
    h = PARAMS.hover_thrust_n
    for _ in range(40):
        quad.step(h * 1.1, h * 0.9, h * 0.9, h * 1.1)  # left side (+y) pushes harder
    assert quad.wx > 0  # positive roll about body x
    rng = np.random.default_rng(0)
    for _ in range(2000):
        quad.step(*rng.uniform(0, PARAMS.max_motor_thrust_n, 4))
    R = quad.R_flight_body
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)


def test_controller_holds_hover_within_a_millimetre():
    quad, ctrl = make_quad((0.5, -0.5, 1.0), yaw=0.3)
    track = fly(quad, ctrl, Setpoint((0.5, -0.5, 1.0), 0.3), 10.0)
    assert np.abs(track[:, :3] - [0.5, -0.5, 1.0]).max() < 1e-3


def test_controller_recovers_from_a_disturbance():
    quad, ctrl = make_quad((0.0, 0.0, 1.0))
    quad.vx, quad.vz, quad.wx, quad.wy = 1.5, -0.5, 3.0, -2.0
    track = fly(quad, ctrl, Setpoint((0.0, 0.0, 1.0), 0.0), 4.0)
    assert np.linalg.norm(track[-1, :3] - [0.0, 0.0, 1.0]) < 0.02
    assert np.linalg.norm(track[:, :3] - [0.0, 0.0, 1.0], axis=1).max() < 0.5


def test_step_in_hover_position_reached_in_4_s_within_limits():
    quad, ctrl = make_quad((0.0, 0.0, 1.0))
    goal = np.array([2.0, 1.0, 1.5])
    track = fly(quad, ctrl, Setpoint(goal, 1.0), 4.0)
    assert np.linalg.norm(track[-1, :3] - goal) < 0.03  # within 3 cm after 4 s
    assert track[:, 5].max() <= math.radians(CONFIG.max_tilt_deg) + math.radians(2.0)
    assert track[:, 3].max() <= CONFIG.max_speed_m_s
    assert np.abs(track[:, 4]).max() <= CONFIG.max_climb_rate_m_s * 1.05
    overshoot = np.dot(track[:, :3] - goal, (goal - [0, 0, 1]) / np.linalg.norm(goal - [0, 0, 1]))
    assert overshoot.max() < 0.05  # the sqrt controller brakes in time
    assert quad.yaw_rad == pytest.approx(1.0, abs=0.01)


def test_long_step_saturates_at_max_speed():
    quad, ctrl = make_quad((0.0, 0.0, 1.0))
    track = fly(quad, ctrl, Setpoint((15.0, 0.0, 1.0), 0.0), 4.0)
    assert track[:, 3].max() == pytest.approx(CONFIG.max_speed_m_s, rel=0.03)
    assert track[:, 5].max() <= math.radians(CONFIG.max_tilt_deg) + math.radians(2.0)


def test_velocity_setpoint_tracked_without_position_hold():
    quad, ctrl = make_quad((0.0, 0.0, 1.0))
    sp = Setpoint((0.0, 0.0, 1.0), 0.0)
    sp.hold_xy = sp.hold_z = False
    sp.vx, sp.vy, sp.vz = 0.5, -0.8, 0.3
    fly(quad, ctrl, sp, 3.0)
    np.testing.assert_allclose(quad.velocity, [0.5, -0.8, 0.3], atol=0.01)


def test_config_rejects_bad_values_with_clear_messages():
    with pytest.raises(ConfigError, match="physics_hz"):
        SimulationConfig(physics_hz=100)
    with pytest.raises(ConfigError, match="radius_m"):
        SimulationConfig(radius_m=-0.1)
    with pytest.raises(ConfigError, match="cannot lift"):
        SimulationConfig(mass_kg=2.0)
    with pytest.raises(ConfigError, match="cruise_speed"):
        SimulationConfig(cruise_speed_m_s=4.0)
