"""The pilot's flight modes besides position hold: angle (self-levelling) and acro (rate).

Sticks ``(throttle, yaw, pitch, roll)`` each in -1..1, with RC conventions in the body frame
(x forward, y left, z up, so positive angles and rates follow the right-hand rule about those
axes): pitch forward (+1) tips the nose down (positive rotation about body y) and flies
forward, roll right (+1) lowers the right side (positive rotation about body x) and flies
right, yaw +1 turns counter-clockwise seen from above (positive about z).

- **angle**: roll and pitch sticks command the tilt, ``expo(stick) * angle_max_deg``, as
  Euler angles in the heading frame (R = Rz(yaw) Ry(pitch) Rx(roll)); the yaw stick commands
  the yaw rate ``expo(stick) * rate_yaw_deg_s``. Centred sticks level the drone; nothing holds
  its position or height. The tilt setpoint moves towards the stick's at most at half the rate
  limits, then through the same first-order filter as acro's rates (below), so it never jumps
  and the drone can follow it. Throttle is collective thrust around hover, divided by
  cos(tilt) (angle boost, as ArduPilot's stabilize mode), so centred throttle holds the height
  roughly whatever the tilt.
- **acro**: the sticks command body rates ``expo(stick) * rate_<axis>_deg_s``; the attitude
  setpoint integrates them, so centred sticks keep the attitude (no self-levelling), whatever
  it is, upside down included. The commanded rates pass a first-order filter with the time
  constant the airframe can follow (1 / rate_gain + the motors' lag) before they are
  integrated: the integral, hence the angle a held stick turns, is unchanged, and the drone
  tracks the setpoint instead of overshooting it. Throttle is raw collective thrust around
  hover.

Both run the same inner loops: the attitude error (Lee et al. 2010, as ``control.py``) ->
body rates with the setpoint's own rates as feed-forward, each clipped to its rate limit ->
torques (rate loop with gyroscopic compensation, and the setpoint's angular acceleration as
feed-forward, so the drone keeps up with the setpoint instead of lagging, then overshooting
it) -> the mixer. Throttle t maps linearly on either side of hover: t = -1 -> MIN_THRUST_G of
the weight, 0 -> hover, +1 -> MAX_THRUST_FRACTION of the four motors' full thrust.

Expo: the cubic ``(1 - e) s + e s^3`` (``stick_expo`` = e in [0, 1)): full stick still gives
the full angle or rate, the centre is (1 - e) times as sensitive as linear.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum
from typing import Any

from server.simulation.config import SimulationConfig
from server.simulation.control import (
    MAX_THRUST_FRACTION,
    MIN_THRUST_G,
    ControlGains,
    Setpoint,
    wrap_angle,
)
from server.simulation.quadrotor import Quadrotor, QuadrotorParams, mix_with, quaternion_rotation

# Angle mode tilts its setpoint at most at this share of the rate limits: the rest is headroom
# for the yaw turning it and for the attitude loop's corrections.
ANGLE_SLEW_SHARE = 0.5
# The attitude setpoint never runs further ahead of the drone than this (rad): a drone held
# back (saturated motors, a wall) does not wind up a flip it would fly later.
MAX_ATTITUDE_LAG_RAD = math.radians(30.0)

Quaternion = tuple[float, float, float, float]  # (w, x, y, z), body to flight frame


class FlightMode(str, Enum):
    """How the sticks fly the drone, named as in the protocol's ``flight_mode``."""

    POSITION = "position"  # sticks command velocities; centred holds position (control.py)
    ANGLE = "angle"
    ACRO = "acro"


def expo(stick: float, e: float) -> float:
    """The cubic expo curve ``(1 - e) s + e s^3`` of a stick ``s`` in -1..1."""
    return (1.0 - e) * stick + e * stick * stick * stick


@dataclass(frozen=True)
class StickRates:
    """What full stick means in angle and acro (rad, rad/s) and the expo."""

    angle_max_rad: float
    roll_rate_rad_s: float
    pitch_rate_rad_s: float
    yaw_rate_rad_s: float
    expo: float

    @classmethod
    def from_config(cls, config: SimulationConfig) -> StickRates:
        return cls(
            angle_max_rad=math.radians(config.angle_max_deg),
            roll_rate_rad_s=math.radians(config.rate_roll_deg_s),
            pitch_rate_rad_s=math.radians(config.rate_pitch_deg_s),
            yaw_rate_rad_s=math.radians(config.rate_yaw_deg_s),
            expo=config.stick_expo,
        )


# Quaternion helpers (scalar floats: this runs at the physics rate)


def _mul(a: Quaternion, b: Quaternion) -> Quaternion:
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    )


def _normalised(q: Quaternion) -> Quaternion:
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    return (q[0] / n, q[1] / n, q[2] / n, q[3] / n)


def _from_euler(roll: float, pitch: float, yaw: float) -> Quaternion:
    """Rz(yaw) Ry(pitch) Rx(roll) as a quaternion."""
    cr, sr = math.cos(0.5 * roll), math.sin(0.5 * roll)
    cp, sp = math.cos(0.5 * pitch), math.sin(0.5 * pitch)
    cy, sy = math.cos(0.5 * yaw), math.sin(0.5 * yaw)
    return (
        cy * cp * cr + sy * sp * sr,
        cy * cp * sr - sy * sp * cr,
        cy * sp * cr + sy * cp * sr,
        sy * cp * cr - cy * sp * sr,
    )


def _rotation(q: Quaternion) -> tuple[float, ...]:
    """R (row-major, 9 floats) of a unit quaternion (w, x, y, z)."""
    return quaternion_rotation(*q)


def euler_from_rotation(R: tuple[float, ...]) -> tuple[float, float, float]:
    """(roll, pitch, yaw) in rad of R = Rz(yaw) Ry(pitch) Rx(roll) (row-major, 9 floats):
    roll about body x (positive: right side down), pitch about body y (positive: nose down),
    yaw about z (counter-clockwise from flight x). Pitch is in [-pi/2, pi/2]."""
    pitch = math.asin(min(1.0, max(-1.0, -R[6])))
    return math.atan2(R[7], R[8]), pitch, math.atan2(R[3], R[0])


def _angle_between(a: Quaternion, b: Quaternion) -> float:
    d = abs(a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + a[3] * b[3])
    return 2.0 * math.acos(min(1.0, d))


def _towards(a: Quaternion, b: Quaternion, fraction: float) -> Quaternion:
    """The rotation ``fraction`` of the way from ``a`` to ``b`` (normalised lerp: close
    enough to slerp for the small angles it is used on)."""
    if a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + a[3] * b[3] < 0:
        b = (-b[0], -b[1], -b[2], -b[3])
    return _normalised(
        (
            a[0] + fraction * (b[0] - a[0]),
            a[1] + fraction * (b[1] - a[1]),
            a[2] + fraction * (b[2] - a[2]),
            a[3] + fraction * (b[3] - a[3]),
        )
    )


class PilotController:
    """Angle and acro flight: sticks -> attitude setpoint -> body rates -> motor thrusts.

    ``engaged`` is False until the first ``update`` after ``release``: that update starts the
    setpoint from the drone's attitude, so taking over never jumps. Switching between angle and
    acro keeps the setpoint where it is."""

    def __init__(self, params: QuadrotorParams, gains: ControlGains, rates: StickRates) -> None:
        self.params = params
        self.gains = gains
        self.rates = rates
        self.engaged = False
        self.mode = FlightMode.ANGLE
        self.q_sp: Quaternion = (1.0, 0.0, 0.0, 0.0)  # attitude setpoint, body to flight
        self.euler_sp = (0.0, 0.0, 0.0)  # angle mode's (roll, pitch, yaw) setpoint, rad
        self.tilt_slew = (0.0, 0.0)  # angle mode's (roll, pitch) before the filter, rad
        self.w_sp = (0.0, 0.0, 0.0)  # acro's filtered body-rate command, rad/s
        self.ff_prev: tuple[float, float, float] | None = None  # last rate feed-forward, rad/s
        self._rate_tau = 1.0 / gains.rate + params.motor_time_constant_s
        self._weight = params.mass_kg * params.gravity_m_s2
        self._max_thrust = MAX_THRUST_FRACTION * 4.0 * params.max_motor_thrust_n
        self._min_boost_cos = math.cos(rates.angle_max_rad)
        # The mixer's constants (quadrotor.mix_with), worked out once.
        self._mixer = (
            params.arm_length_m / math.sqrt(2.0),
            params.yaw_moment_m,
            params.max_motor_thrust_n,
        )

    def release(self) -> None:
        """Another mode flies the drone now; the next update takes over from its attitude."""
        self.engaged = False

    def state(self) -> tuple[object, ...]:
        """Everything ``update`` changes, for ``set_state`` (rewinding a physics step)."""
        return (
            self.engaged,
            self.mode,
            self.q_sp,
            self.euler_sp,
            self.tilt_slew,
            self.w_sp,
            self.ff_prev,
        )

    def set_state(self, state: tuple[Any, ...]) -> None:
        (
            self.engaged,
            self.mode,
            self.q_sp,
            self.euler_sp,
            self.tilt_slew,
            self.w_sp,
            self.ff_prev,
        ) = state

    def collective_n(self, throttle: float) -> float:
        """Collective thrust (N) for a throttle stick in -1..1: hover at 0."""
        w = self._weight
        if throttle >= 0.0:
            return w + throttle * (self._max_thrust - w)
        return w + throttle * (w - MIN_THRUST_G * w)

    def update(
        self,
        q: Quadrotor,
        mode: FlightMode,
        sticks: tuple[float, float, float, float],
    ) -> tuple[float, float, float, float]:
        """Motor thrust commands (N) for one step of ``mode`` (ANGLE or ACRO)."""
        throttle, yaw, pitch, roll = sticks
        r = self.rates
        e = r.expo
        dt = q.dt
        if not self.engaged or mode != self.mode:
            self.ff_prev = None  # a new setpoint: no acceleration feed-forward from the old one
        if not self.engaged:
            self.engaged = True
            self.q_sp = (q.qw, q.qx, q.qy, q.qz)
            self.euler_sp = euler_from_rotation(q.rotation())
            self.tilt_slew = self.euler_sp[:2]
            self.w_sp = (q.wx, q.wy, q.wz)
        elif mode != self.mode and mode == FlightMode.ANGLE:
            self.euler_sp = euler_from_rotation(_rotation(self.q_sp))
            self.tilt_slew = self.euler_sp[:2]
        elif mode != self.mode:
            self.w_sp = (q.wx, q.wy, q.wz)
        self.mode = mode
        R = q.rotation()
        q_now = (q.qw, q.qx, q.qy, q.qz)

        k = dt / (self._rate_tau + dt)  # the first-order filter's step
        if mode == FlightMode.ANGLE:
            # Tilt towards the sticks' at most at half the rate limits, then filtered; yaw at the
            # stick's rate (the setpoint kept within MAX_ATTITUDE_LAG_RAD of the heading).
            tr, tp = self.tilt_slew
            step_r = ANGLE_SLEW_SHARE * r.roll_rate_rad_s * dt
            step_p = ANGLE_SLEW_SHARE * r.pitch_rate_rad_s * dt
            tr += min(max(expo(roll, e) * r.angle_max_rad - tr, -step_r), step_r)
            tp += min(max(expo(pitch, e) * r.angle_max_rad - tp, -step_p), step_p)
            self.tilt_slew = (tr, tp)
            r0, p0, y0 = self.euler_sp
            sr, sp = r0 + k * (tr - r0), p0 + k * (tp - p0)
            yaw_rate = expo(yaw, e) * r.yaw_rate_rad_s
            lag = wrap_angle(y0 + yaw_rate * dt - q.yaw_rad)
            sy = wrap_angle(q.yaw_rad + min(max(lag, -MAX_ATTITUDE_LAG_RAD), MAX_ATTITUDE_LAG_RAD))
            self.euler_sp = (sr, sp, sy)
            self.q_sp = _from_euler(sr, sp, sy)
            # Feed-forward: the setpoint's Euler rates as body rates of the setpoint, then in
            # the drone's body axes.
            dr, dp = (sr - r0) / dt, (sp - p0) / dt
            cr, s_r, cp = math.cos(sr), math.sin(sr), math.cos(sp)
            w_sp = (
                dr - yaw_rate * math.sin(sp),
                dp * cr + yaw_rate * cp * s_r,
                -dp * s_r + yaw_rate * cp * cr,
            )
            ffx, ffy, ffz = _rotate_into_body(R, _rotation(self.q_sp), w_sp)
            thrust = self.collective_n(throttle) / max(R[8], self._min_boost_cos)
        else:
            # Filter the commanded body rates, then integrate them into the setpoint:
            # q_sp <- q_sp exp(w dt / 2).
            wx, wy, wz = self.w_sp
            wx += k * (expo(roll, e) * r.roll_rate_rad_s - wx)
            wy += k * (expo(pitch, e) * r.pitch_rate_rad_s - wy)
            wz += k * (expo(yaw, e) * r.yaw_rate_rad_s - wz)
            self.w_sp = (wx, wy, wz)
            n = math.sqrt(wx * wx + wy * wy + wz * wz)
            if n > 0.0:
                s = math.sin(0.5 * n * dt) / n
                self.q_sp = _normalised(
                    _mul(self.q_sp, (math.cos(0.5 * n * dt), wx * s, wy * s, wz * s))
                )
            lag = _angle_between(self.q_sp, q_now)
            if lag > MAX_ATTITUDE_LAG_RAD:
                self.q_sp = _towards(q_now, self.q_sp, MAX_ATTITUDE_LAG_RAD / lag)
            # Feed-forward: the commanded rates, from the setpoint's body axes into the drone's.
            Rd = _rotation(self.q_sp)
            ffx, ffy, ffz = _rotate_into_body(R, Rd, (wx, wy, wz))
            thrust = self.collective_n(throttle)
        return self._track(q, R, _rotation(self.q_sp), (ffx, ffy, ffz), thrust)

    def _track(
        self,
        q: Quadrotor,
        R: tuple[float, ...],
        Rd: tuple[float, ...],
        feed_forward: tuple[float, float, float],
        thrust_n: float,
    ) -> tuple[float, float, float, float]:
        """Attitude error -> body rates (clipped to the rate limits) -> torques -> motors."""
        g, r = self.gains, self.rates
        ffx, ffy, ffz = feed_forward
        prev = self.ff_prev or feed_forward
        self.ff_prev = feed_forward
        dt = q.dt
        ax, ay, az = (ffx - prev[0]) / dt, (ffy - prev[1]) / dt, (ffz - prev[2]) / dt
        # e_R = vee(M - M^T) / 2 with M = Rd^T R.
        m01 = Rd[0] * R[1] + Rd[3] * R[4] + Rd[6] * R[7]
        m02 = Rd[0] * R[2] + Rd[3] * R[5] + Rd[6] * R[8]
        m10 = Rd[1] * R[0] + Rd[4] * R[3] + Rd[7] * R[6]
        m12 = Rd[1] * R[2] + Rd[4] * R[5] + Rd[7] * R[8]
        m20 = Rd[2] * R[0] + Rd[5] * R[3] + Rd[8] * R[6]
        m21 = Rd[2] * R[1] + Rd[5] * R[4] + Rd[8] * R[7]
        wdx = ffx - g.attitude * 0.5 * (m21 - m12)
        wdy = ffy - g.attitude * 0.5 * (m02 - m20)
        wdz = ffz - g.attitude * 0.5 * (m10 - m01)
        # At a rate limit the setpoint's acceleration no longer applies: the drone holds it.
        if abs(wdx) >= r.roll_rate_rad_s:
            wdx, ax = math.copysign(r.roll_rate_rad_s, wdx), 0.0
        if abs(wdy) >= r.pitch_rate_rad_s:
            wdy, ay = math.copysign(r.pitch_rate_rad_s, wdy), 0.0
        if abs(wdz) >= r.yaw_rate_rad_s:
            wdz, az = math.copysign(r.yaw_rate_rad_s, wdz), 0.0
        ixx, iyy, izz = self.params.inertia_kg_m2
        wx, wy, wz = q.wx, q.wy, q.wz
        tx = ixx * (g.rate * (wdx - wx) + ax) + (izz - iyy) * wy * wz
        ty = iyy * (g.rate * (wdy - wy) + ay) + (ixx - izz) * wz * wx
        tz = izz * (g.rate * (wdz - wz) + az) + (iyy - ixx) * wx * wy
        thrust_n = 0.0 if thrust_n < 0.0 else thrust_n  # min(max(t, 0), max), as comparisons
        thrust_n = self._max_thrust if self._max_thrust < thrust_n else thrust_n
        a_, k_, f_max = self._mixer
        return mix_with(a_, k_, f_max, thrust_n, tx, ty, tz)


def _rotate_into_body(
    R: tuple[float, ...], Rd: tuple[float, ...], w: tuple[float, float, float]
) -> tuple[float, float, float]:
    """R^T Rd w: a rate vector in the setpoint's body axes, in the drone's body axes."""
    x, y, z = w
    fx = Rd[0] * x + Rd[1] * y + Rd[2] * z
    fy = Rd[3] * x + Rd[4] * y + Rd[5] * z
    fz = Rd[6] * x + Rd[7] * y + Rd[8] * z
    return (
        R[0] * fx + R[3] * fy + R[6] * fz,
        R[1] * fx + R[4] * fy + R[7] * fz,
        R[2] * fx + R[5] * fy + R[8] * fz,
    )


def hand_over_to_position(sp: Setpoint, q: Quadrotor) -> None:
    """Position mode takes over from angle or acro (mode switch, or stale sticks): brake from
    the current velocity, then hold where the drone stops (``fly_sticks`` latches), facing
    where it faces now."""
    sp.hold_xy = sp.hold_z = False
    sp.vx = sp.vy = sp.vz = 0.0
    sp.ax = sp.ay = sp.az = 0.0
    sp.yaw, sp.yaw_rate = q.yaw_rad, 0.0
