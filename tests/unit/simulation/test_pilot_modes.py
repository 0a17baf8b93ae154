"""The pilot's flight modes angle and acro (server.simulation.pilot_modes) in the drone simulator:
what each stick does, levelling or keeping the attitude when centred, rate limits, the expo
curve, switching modes mid-flight, stale sticks and collisions. Pure simulation, faster than
real time; tolerances are stated in each test."""

from __future__ import annotations

import math

import numpy as np
import pytest

from server.errors import ConfigError
from server.simulation.config import SimulationConfig
from server.simulation.drone import DroneSimulator
from server.simulation.drone_types import DroneCommandError, DroneEventKind, DroneMode
from server.simulation.flight_map import FlightMap
from server.simulation.pilot_modes import FlightMode, euler_from_rotation, expo
from server.simulation.scenes import room_with_door

CONFIG = SimulationConfig()
R = CONFIG.radius_m
DT = CONFIG.dt_s
MAX_ANGLE = CONFIG.angle_max_deg
RATES = np.array([CONFIG.rate_roll_deg_s, CONFIG.rate_pitch_deg_s, CONFIG.rate_yaw_deg_s])
E = CONFIG.stick_expo
CENTRED = (0.0, 0.0, 0.0, 0.0)
HALL_START = np.array([5.0, 5.0, 3.0])


def hall() -> FlightMap:
    """A 10 x 10 x 6 m hall (walls 0.2 m thick), room to fly fast for a few seconds."""
    size, t = np.array([10.0, 10.0, 6.0]), 0.2
    lo, hi = -t * np.ones(3), size + t
    boxes = [(lo, np.array([hi[0], hi[1], 0.0])), (np.array([lo[0], lo[1], size[2]]), hi)]
    boxes += [(lo, np.array([0.0, hi[1], hi[2]])), (np.array([size[0], lo[1], lo[2]]), hi)]
    boxes += [(lo, np.array([hi[0], 0.0, hi[2]])), (np.array([lo[0], size[1], lo[2]]), hi)]
    return FlightMap.from_boxes(lo, hi, boxes, voxel_m=0.1)


HALL = hall()


class Flight:
    """A drone in a mode, flown one physics step per sample with sticks at 20 Hz; records
    time, Euler angles (deg), body rates (deg/s), position and velocity at every step."""

    def __init__(self, mode: str, flight_map: FlightMap = HALL, at=HALL_START, yaw=0.0) -> None:
        self.drone = DroneSimulator(CONFIG, flight_map)
        self.drone.spawn(np.asarray(at, float), yaw_rad=yaw)
        self.drone.set_flight_mode(mode)
        self.rows: list[tuple] = []
        self.events: list = []

    @property
    def quad(self):
        return self.drone._modes.quad

    def fly(self, sticks, seconds: float, send: bool = True) -> np.ndarray:
        """This stretch's rows: t, roll, pitch, yaw, wx, wy, wz, x, y, z, vx, vy, vz."""
        q = self.quad
        start = len(self.rows)
        for i in range(round(seconds / DT)):
            if send and i % round(0.05 / DT) == 0:
                self.drone.command_sticks(sticks)
            self.events += self.drone.advance(DT)
            angles = np.degrees(euler_from_rotation(q.rotation()))
            rates = np.degrees((q.wx, q.wy, q.wz))
            self.rows.append(
                (self.drone.time_s, *angles, *rates, q.px, q.py, q.pz, q.vx, q.vy, q.vz)
            )
        return np.array(self.rows[start:])

    def tilt_deg(self) -> float:
        return math.degrees(self.quad.tilt_rad)


def test_expo_curve_at_0_half_and_full_stick():
    # (1 - e) s + e s^3: full stick keeps full scale, the centre is softer.
    for e in (0.0, 0.3, 0.7):
        assert expo(0.0, e) == 0.0
        assert expo(1.0, e) == pytest.approx(1.0)
        assert expo(-1.0, e) == pytest.approx(-1.0)
        assert expo(0.5, e) == pytest.approx(0.5 - 0.375 * e)
        assert expo(-0.5, e) == pytest.approx(-(0.5 - 0.375 * e))
    assert expo(0.5, 0.0) == 0.5  # e = 0: linear
    assert expo(0.5, 0.3) == pytest.approx(0.3875)  # the default


def test_expo_and_angle_settings_are_checked():
    SimulationConfig(stick_expo=0.0)  # linear is allowed
    for bad in ({"stick_expo": 1.0}, {"stick_expo": -0.1}, {"angle_max_deg": 85.0}):
        with pytest.raises(ConfigError):
            SimulationConfig(**bad)
    with pytest.raises(ConfigError, match="rate_roll_deg_s"):
        SimulationConfig(rate_roll_deg_s=0.0)


def test_angle_full_pitch_tilts_to_the_max_angle_and_accelerates_forward():
    yaw = math.radians(60.0)
    f = Flight("angle", yaw=yaw)
    track = f.fly((0.0, 0.0, 1.0, 0.0), 1.0)
    t, roll, pitch, heading = track[:, 0], track[:, 1], track[:, 2], track[:, 3]
    settled = t >= t[0] + 0.5
    # Within 0.5 s the nose is down by the max angle (+-2.5 deg), level sideways, same heading.
    assert np.all(np.abs(pitch[settled] - MAX_ANGLE) < 2.5), (pitch[settled].min(), pitch.max())
    assert np.abs(roll).max() < 1.0
    assert np.abs(heading - math.degrees(yaw)).max() < 1.0
    # It accelerates along its heading (g tan 40 deg = 8.2 m/s^2 less drag), not sideways,
    # and the angle boost keeps its height within 0.15 m.
    v = track[-1, 10:13]
    forward = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    assert v @ forward > 5.0
    assert abs(v @ np.array([-math.sin(yaw), math.cos(yaw), 0.0])) < 0.1
    assert np.abs(track[:, 9] - HALL_START[2]).max() < 0.15
    assert f.drone.status().mode == DroneMode.MANUAL
    assert f.drone.status().flight_mode == FlightMode.ANGLE


def test_angle_centred_sticks_level_within_half_a_second_without_holding_position():
    f = Flight("angle")
    f.fly((0.0, 0.0, 0.0, 1.0), 0.3)  # full roll right: flies towards -y
    z0 = f.quad.pz
    track = f.fly(CENTRED, 1.5)
    t = track[:, 0] - track[0, 0]
    tilt = np.hypot(track[:, 1], track[:, 2])
    assert np.all(tilt[t >= 0.5] < 2.0), tilt[t >= 0.5].max()  # level within 0.5 s
    # Levelled, not braked: it glides on (drag only), nothing pulls it back.
    vy = track[:, 11]
    assert vy[0] < -0.8 and np.all(np.diff(vy[t >= 0.5]) >= -1e-9)  # no braking beyond drag
    assert vy[-1] < 0.7 * vy.min()  # still 70 % of its top speed after 1.5 s
    assert not f.events[1:]  # nothing hit
    # Centred throttle is hover thrust: the height drifts by less than 0.2 m.
    assert np.abs(track[:, 9] - z0).max() < 0.2


def test_angle_throttle_climbs_and_yaw_stick_turns_at_its_rate():
    f = Flight("angle")
    track = f.fly((0.2, 0.5, 0.0, 0.0), 1.0)
    assert not f.events[1:]
    assert track[-1, 12] > 1.0  # climbing: throttle 0.2 is a fifth of the way to full thrust
    yaw_rate = np.gradient(np.unwrap(np.radians(track[:, 3])), track[:, 0])
    expected = expo(0.5, E) * CONFIG.rate_yaw_deg_s
    assert np.degrees(yaw_rate[-100:]).mean() == pytest.approx(expected, rel=0.03)


def test_acro_roll_turns_by_rate_times_time_then_keeps_the_attitude():
    f = Flight("acro")
    f.fly(CENTRED, 0.2)
    held_s = 0.2
    f.fly((0.0, 0.0, 0.0, 0.25), held_s)
    expected = expo(0.25, E) * CONFIG.rate_roll_deg_s * held_s  # 14.4 deg
    after = f.fly(CENTRED, 1.5)
    t = after[:, 0] - after[0, 0]
    roll = after[:, 1]
    # The attitude ends where the rates integrate to (+-1.5 deg) and stays there: no levelling.
    assert np.all(np.abs(roll[t >= 0.6] - expected) < 1.5), (roll[t >= 0.6], expected)
    assert np.abs(after[t >= 0.6, 2]).max() < 1.0 and np.abs(after[:, 3]).max() < 1.0
    assert f.tilt_deg() > expected - 1.5
    # ... and so it accelerates sideways (right: -y) and sinks (no angle boost in acro).
    assert not f.events[1:]
    assert after[-1, 11] < -2.0 and after[-1, 12] < -0.1


def test_acro_pitch_and_yaw_sticks_integrate_too():
    f = Flight("acro")
    f.fly((0.0, 1.0, -0.4, 0.0), 0.25)  # full yaw left, some pitch back (nose up)
    after = f.fly(CENTRED, 0.8)[-1]
    yaw_expected = CONFIG.rate_yaw_deg_s * 0.25
    pitch_expected = expo(-0.4, E) * CONFIG.rate_pitch_deg_s * 0.25
    R_now = f.drone.status().T_flight_drone[:3, :3]
    # Rotation about body axes: compare the whole attitude with the integrated setpoint.
    w = np.radians([0.0, pitch_expected / 0.25, yaw_expected / 0.25])
    angle = np.linalg.norm(w) * 0.25
    axis = w / np.linalg.norm(w)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    R_expected = np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K
    error = math.degrees(math.acos(np.clip((np.trace(R_expected.T @ R_now) - 1) / 2, -1, 1)))
    assert error < 2.0, (error, after[1:4])


def test_rate_limits_hold_in_acro_and_angle():
    # Full stick one way, then the other (a rate step of twice the limit), axis by axis: the
    # airframe reaches the limit and overshoots it by at most 5 % (the motors' lag).
    for axis, stick in ((0, (0.0, 0.0, 0.0, 1.0)), (1, (0.0, 0.0, 1.0, 0.0))):
        f = Flight("acro")
        a = f.fly(stick, 0.15)
        b = f.fly(tuple(-s for s in stick), 0.15)
        f.fly(CENTRED, 0.3)
        rates = np.abs(np.vstack([a, b])[:, 4:7]).max(axis=0)
        assert 0.95 * RATES[axis] <= rates[axis] <= 1.05 * RATES[axis], (axis, rates)
        assert not f.events[1:]
    f = Flight("acro")
    yaw = np.abs(f.fly((0.0, 1.0, 0.0, 0.0), 1.0)[:, 6])  # yaw has the least torque: slower
    assert 0.97 * RATES[2] <= yaw.max() <= 1.03 * RATES[2]
    # Every stick full at once saturates the motors (the mixer clips): within 12 %.
    f = Flight("acro")
    a = f.fly((0.0, 1.0, 1.0, 1.0), 0.15)
    b = f.fly((0.0, -1.0, -1.0, -1.0), 0.15)
    assert np.all(np.abs(np.vstack([a, b])[:, 4:7]).max(axis=0) <= 1.12 * RATES)
    # Angle mode: full pitch one way, then the other, within 5 % of the limits; every stick
    # reversed at once (motors saturated) within 12 %, and the tilt within the max angles.
    g = Flight("angle")
    steps = np.vstack([g.fly((0.0, 0.0, 1.0, 0.0), 0.5), g.fly((0.0, 0.0, -1.0, 0.0), 0.5)])
    assert np.all(np.abs(steps[:, 4:7]).max(axis=0) <= 1.05 * RATES)
    g = Flight("angle")
    steps = g.fly((0.0, 1.0, 1.0, -1.0), 0.6)
    steps = np.vstack([steps, g.fly((0.0, -1.0, -1.0, 1.0), 0.6)])
    assert np.all(np.abs(steps[:, 4:7]).max(axis=0) <= 1.12 * RATES)
    assert np.hypot(steps[:, 1], steps[:, 2]).max() < math.hypot(MAX_ANGLE, MAX_ANGLE) + 3.0


def test_the_mixer_survives_a_negligible_yaw_torque_with_a_motor_saturated():
    from server.simulation.quadrotor import QuadrotorParams, mix

    params = QuadrotorParams.from_config(CONFIG)
    f = mix(params, 4 * params.max_motor_thrust_n, 0.2, 0.0, 1e-18)  # used to divide by 0
    assert all(0.0 <= x <= params.max_motor_thrust_n for x in f)


def test_switching_modes_mid_flight_never_jumps():
    f = Flight("position", at=(2.0, 2.0, 3.0), yaw=math.pi / 4)
    sticks = (0.0, 0.3, 1.0, 0.0)
    f.fly(sticks, 0.8)  # position mode: towards 3 m/s forward, turning
    rows = []
    for mode, stick, seconds in (
        ("angle", (0.0, 0.3, 0.3, 0.2), 0.5),
        ("acro", (0.0, 0.0, 0.0, 0.3), 0.3),
        ("angle", (0.0, 0.3, -0.5, 0.0), 0.6),
        ("position", sticks, 0.8),
        ("acro", CENTRED, 0.4),
    ):
        f.drone.set_flight_mode(mode)
        rows.append(f.fly(stick, seconds))
        assert f.drone.status().flight_mode.value == mode
    track = np.vstack(rows)
    # Body rates within the limits throughout, and the attitude moves continuously: no step
    # turns it by more than the fastest rate allows.
    assert np.all(np.abs(track[:, 4:7]).max(axis=0) <= 1.03 * RATES)
    turn = np.abs(np.diff(np.unwrap(np.radians(track[:, 1:4]), axis=0), axis=0))
    assert np.degrees(turn).max() <= 1.03 * RATES.max() * DT
    assert not [e for e in f.events if e.kind == DroneEventKind.COLLISION]


def _setpoint_rotation(f: Flight):
    from server.simulation.pilot_modes import _rotation

    return _rotation(f.drone._modes.manual.pilot.q_sp)


def test_taking_over_starts_from_the_attitude_flown():
    f = Flight("position")
    f.fly((0.0, 0.0, 1.0, 0.5), 0.4)  # accelerating: tilted
    tilted = f.quad.rotation()
    assert f.tilt_deg() > 10.0
    for mode in ("angle", "acro"):
        f.drone.set_flight_mode(mode)
        f.drone.command_sticks((0.0, 0.0, 1.0, 0.5))
        f.drone.advance(DT)
        # After one step the setpoint is the attitude the drone had (within one step of turning).
        Rd = np.array(_setpoint_rotation(f)).reshape(3, 3)
        R0 = np.array(tilted).reshape(3, 3)
        error = math.degrees(math.acos(np.clip((np.trace(Rd.T @ R0) - 1) / 2, -1, 1)))
        assert error < RATES.max() * DT * 1.5, (mode, error)
        f.drone.set_flight_mode("position")
        f.fly((0.0, 0.0, 1.0, 0.5), 0.2)
        tilted = f.quad.rotation()


def test_back_to_position_mode_brakes_and_holds():
    f = Flight("angle")
    f.fly((0.0, 0.0, 1.0, 0.0), 0.5)
    assert f.quad.vx > 2.0
    f.drone.set_flight_mode("position")
    f.fly(CENTRED, 3.0)
    held = f.quad.position
    track = f.fly(CENTRED, 1.0)
    assert np.abs(track[:, 7:10] - held).max() < 0.01  # holds its position again
    assert f.drone.status().mode == DroneMode.MANUAL


def test_stale_sticks_in_acro_brake_and_hold_instead_of_flying_on():
    f = Flight("acro")
    f.fly((0.0, 0.0, 0.3, 0.0), 0.3)  # nose down and centred: accelerating forward
    f.fly(CENTRED, 0.3)
    assert f.tilt_deg() > 10.0
    # The link drops: no more sticks. After stick_timeout_s position mode brakes and holds.
    track = f.fly(CENTRED, 4.0, send=False)
    t = track[:, 0] - track[0, 0]
    speed = np.linalg.norm(track[:, 10:13], axis=1)
    assert np.all(speed[t > 3.0] < 0.05) and np.all(
        np.hypot(track[t > 3.0, 1], track[t > 3.0, 2]) < 1
    )
    assert f.drone.status().flight_mode == FlightMode.ACRO  # the setting stays


@pytest.mark.parametrize("mode", ["angle", "acro"])
def test_flown_into_a_wall_in_angle_and_acro_collides_on_the_near_side(mode):
    scene = room_with_door()  # wall face at x = 1.9 for y < 1.2
    f = Flight(mode, scene.flight_map, at=scene.start)
    wall_x = 1.9
    if mode == "angle":
        track = f.fly((0.0, 0.0, 0.6, 0.0), 2.0)
    else:
        f.fly((0.0, 0.0, 0.3, 0.0), 0.2)  # tip the nose down, then let go: it flies on
        track = f.fly(CENTRED, 2.0)
    # A bump or, this fast (over crash_speed_m_s along the wall's normal), a crash.
    hits = [e for e in f.events if e.kind in (DroneEventKind.COLLISION, DroneEventKind.CRASH)]
    assert hits, "no collision"
    assert wall_x - R - 0.05 < hits[0].position[0] <= wall_x - R
    assert track[:, 7].max() <= wall_x - R + 1e-9  # the sphere never entered the wall


def test_an_unknown_flight_mode_is_refused_and_changes_nothing():
    f = Flight("angle")
    for bad in ("Angle", "rate", "", None, 3):
        with pytest.raises(DroneCommandError, match="position, angle, acro"):
            f.drone.set_flight_mode(bad)  # type: ignore[arg-type]
        assert f.drone.flight_mode == FlightMode.ANGLE
    # Before spawn too: the setting waits for the drone.
    d = DroneSimulator(CONFIG, HALL)
    d.set_flight_mode("acro")
    d.spawn(HALL_START)
    assert d.status().flight_mode == FlightMode.ACRO and d.status().mode == DroneMode.HOVER
