"""Cascaded quadrotor controller: position -> velocity -> acceleration/attitude -> body rates ->
torques, plus collective thrust, with limits on speed, climb rate, acceleration, tilt and yaw rate.

Each loop is a proportional controller with its own bandwidth (1/s); the route's velocity and
acceleration enter as feed-forward, gravity and drag are compensated exactly (the model is known).
The attitude loop is the geometric controller of Lee et al. (2010): the desired body z is the
direction of the required thrust, the desired heading fixes body x; the error is
``e_R = vee(R_d^T R - R^T R_d) / 2``. Scalar float arithmetic throughout, like the dynamics.

A setpoint holds, per axis group (horizontal, vertical), either a position with velocity and
acceleration feed-forward, or only a velocity (manual flight). ``fly_sticks`` and
``RouteTracker`` turn the pilot's sticks and a planned route into setpoints.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, fields

import numpy as np

from server.geometry.arrays import FloatArray
from server.simulation.config import SimulationConfig
from server.simulation.quadrotor import Quadrotor, QuadrotorParams, mix_with, quaternion_rotation
from server.simulation.route import Route

MAX_TILT_RATE_RAD_S = 6.0  # body roll/pitch rate the attitude loop may ask for
MIN_THRUST_G = 0.25  # never command less vertical thrust than this fraction of the weight
MAX_THRUST_FRACTION = 0.95  # of the four motors' full thrust


@dataclass(frozen=True)
class ControlGains:
    """Bandwidths of the loops, 1/s."""

    position: float
    velocity: float
    attitude: float
    yaw: float
    rate: float

    @classmethod
    def from_config(cls, config: SimulationConfig) -> ControlGains:
        """The defaults live in SimulationConfig alone (``<loop>_gain``)."""
        return cls(**{f.name: getattr(config, f"{f.name}_gain") for f in fields(cls)})


@dataclass(frozen=True)
class ControlLimits:
    max_speed_m_s: float  # horizontal
    max_climb_rate_m_s: float  # vertical, both ways
    max_accel_m_s2: float
    max_tilt_rad: float
    max_yaw_rate_rad_s: float
    brake_accel_m_s2: float  # position errors are closed no faster than this allows

    @classmethod
    def from_config(cls, config: SimulationConfig) -> ControlLimits:
        """The defaults live in SimulationConfig alone."""
        return cls(
            max_speed_m_s=config.max_speed_m_s,
            max_climb_rate_m_s=config.max_climb_rate_m_s,
            max_accel_m_s2=config.max_accel_m_s2,
            max_tilt_rad=math.radians(config.max_tilt_deg),
            max_yaw_rate_rad_s=math.radians(config.max_yaw_rate_deg_s),
            brake_accel_m_s2=config.route_accel_m_s2,
        )


class Setpoint:
    """What the controller tracks (flight frame, SI units).

    ``hold_xy`` / ``hold_z``: track the position (x, y) / z with the velocity and acceleration
    as feed-forward; otherwise track the velocity alone on those axes. ``yaw`` is the heading
    (rad, counter-clockwise from +x), ``yaw_rate`` its feed-forward (rad/s).
    """

    __slots__ = (
        "x",
        "y",
        "z",
        "vx",
        "vy",
        "vz",
        "ax",
        "ay",
        "az",
        "yaw",
        "yaw_rate",
        "hold_xy",
        "hold_z",
    )

    def __init__(self, position: Iterable[float] = (0.0, 0.0, 0.0), yaw: float = 0.0) -> None:
        self.hold(position, yaw)

    def hold(self, position: Iterable[float], yaw: float) -> None:
        """Hover at ``position`` facing ``yaw``."""
        self.x, self.y, self.z = (float(c) for c in position)
        self.vx = self.vy = self.vz = 0.0
        self.ax = self.ay = self.az = 0.0
        self.yaw, self.yaw_rate = float(yaw), 0.0
        self.hold_xy = self.hold_z = True

    def descend(self, x: float, y: float, speed_m_s: float) -> None:
        """Sink straight down at ``speed_m_s`` over (x, y), heading kept (landing)."""
        self.x, self.y = x, y
        self.vx = self.vy = self.ax = self.ay = self.az = 0.0
        self.hold_xy, self.hold_z, self.yaw_rate = True, False, 0.0
        self.vz = -speed_m_s

    def move_with_world(self, R: FloatArray, t: FloatArray, dyaw_rad: float) -> None:
        """Carry the setpoint with a corrected world (loop closure), as
        ``Quadrotor.move_with_world``: ``R`` (3, 3), ``t`` (3,) m, heading turned by
        ``dyaw_rad``."""
        self.x, self.y, self.z = (float(c) for c in R @ [self.x, self.y, self.z] + t)
        self.vx, self.vy, self.vz = (float(c) for c in R @ [self.vx, self.vy, self.vz])
        self.ax, self.ay, self.az = (float(c) for c in R @ [self.ax, self.ay, self.az])
        self.yaw += dyaw_rad


def _sqrt_controller(error: float, gain: float, accel: float) -> float:
    """Speed that closes ``error`` (m) with gain ``gain`` near zero and at most ``accel`` braking
    far away, so that large steps do not overshoot (as ArduPilot's sqrt controller)."""
    linear = accel / (gain * gain)
    if error > linear:
        return math.sqrt(2.0 * accel * (error - 0.5 * linear))
    if error < -linear:
        return -math.sqrt(2.0 * accel * (-error - 0.5 * linear))
    return gain * error


class CascadedController:
    """Turns the quadrotor's state and a setpoint into four motor thrust commands."""

    def __init__(self, params: QuadrotorParams, gains: ControlGains, limits: ControlLimits) -> None:
        self.params = params
        self.gains = gains
        self.limits = limits
        self._tan_tilt = math.tan(limits.max_tilt_rad)
        self._drag = params.drag_n_s_m / params.mass_kg
        self._max_thrust = MAX_THRUST_FRACTION * 4.0 * params.max_motor_thrust_n
        # The mixer's constants (quadrotor.mix_with), worked out once.
        self._mixer = (
            params.arm_length_m / math.sqrt(2.0),
            params.yaw_moment_m,
            params.max_motor_thrust_n,
        )

    def update(self, q: Quadrotor, sp: Setpoint) -> tuple[float, float, float, float]:
        """Motor thrust commands (N) for this step."""
        g = self.gains
        lim = self.limits
        grav = self.params.gravity_m_s2
        kp = g.position
        brake = lim.brake_accel_m_s2

        # Position -> velocity (horizontal and vertical separately, each limited).
        vx, vy, vz = sp.vx, sp.vy, sp.vz
        if sp.hold_xy:
            ex, ey = sp.x - q.px, sp.y - q.py
            e = math.hypot(ex, ey)
            if e > 1e-9:
                s = _sqrt_controller(e, kp, brake) / e
                vx += s * ex
                vy += s * ey
        if sp.hold_z:
            vz += _sqrt_controller(sp.z - q.pz, kp, brake)
        speed = math.hypot(vx, vy)
        v_max = lim.max_speed_m_s
        if speed > v_max:
            vx *= v_max / speed
            vy *= v_max / speed
        climb = lim.max_climb_rate_m_s
        vz = climb if vz > climb else (-climb if vz < -climb else vz)

        # Velocity -> acceleration (limited), plus feed-forward.
        kv = g.velocity
        qvx, qvy, qvz = q.vx, q.vy, q.vz
        ax = sp.ax + kv * (vx - qvx)
        ay = sp.ay + kv * (vy - qvy)
        az = sp.az + kv * (vz - qvz)
        a = math.sqrt(ax * ax + ay * ay + az * az)
        if a > lim.max_accel_m_s2:
            s = lim.max_accel_m_s2 / a
            ax, ay, az = ax * s, ay * s, az * s

        # Required specific thrust: acceleration + gravity + drag, vertical first, tilt limited.
        drag = self._drag
        fx = ax + drag * qvx
        fy = ay + drag * qvy
        fz = az + grav + drag * qvz
        f_min = MIN_THRUST_G * grav
        if f_min > fz:
            fz = f_min
        h = math.hypot(fx, fy)
        h_max = fz * self._tan_tilt
        if h > h_max:
            fx *= h_max / h
            fy *= h_max / h
        f = math.sqrt(fx * fx + fy * fy + fz * fz)
        zx, zy, zz = fx / f, fy / f, fz / f  # desired body z

        # Desired attitude: body z as above, body x towards the heading.
        cy, sy = math.cos(sp.yaw), math.sin(sp.yaw)
        yx, yy, yz = -zz * sy, zz * cy, zx * sy - zy * cy  # z_d x (cos, sin, 0)
        n = math.sqrt(yx * yx + yy * yy + yz * yz)
        yx, yy, yz = yx / n, yy / n, yz / n
        xx, xy, xz = yy * zz - yz * zy, yz * zx - yx * zz, yx * zy - yy * zx

        # Attitude error e_R = vee(M - M^T) / 2 with M = R_d^T R (only 6 entries needed).
        r00, r01, r02, r10, r11, r12, r20, r21, r22 = quaternion_rotation(q.qw, q.qx, q.qy, q.qz)
        m01 = xx * r01 + xy * r11 + xz * r21
        m02 = xx * r02 + xy * r12 + xz * r22
        m10 = yx * r00 + yy * r10 + yz * r20
        m12 = yx * r02 + yy * r12 + yz * r22
        m20 = zx * r00 + zy * r10 + zz * r20
        m21 = zx * r01 + zy * r11 + zz * r21
        erx = 0.5 * (m21 - m12)
        ery = 0.5 * (m02 - m20)
        erz = 0.5 * (m10 - m01)

        # Attitude -> body rates (limited), yaw rate feed-forward about body z.
        ka = g.attitude
        wdx = -ka * erx
        wdx = -MAX_TILT_RATE_RAD_S if wdx < -MAX_TILT_RATE_RAD_S else wdx
        wdx = MAX_TILT_RATE_RAD_S if wdx > MAX_TILT_RATE_RAD_S else wdx
        wdy = -ka * ery
        wdy = -MAX_TILT_RATE_RAD_S if wdy < -MAX_TILT_RATE_RAD_S else wdy
        wdy = MAX_TILT_RATE_RAD_S if wdy > MAX_TILT_RATE_RAD_S else wdy
        wdz = -g.yaw * erz + sp.yaw_rate * r22
        yaw_max = lim.max_yaw_rate_rad_s
        wdz = -yaw_max if wdz < -yaw_max else wdz
        wdz = yaw_max if wdz > yaw_max else wdz

        # Body rates -> torques (with gyroscopic compensation); thrust along the current body z.
        ixx, iyy, izz = self.params.inertia_kg_m2
        kr = g.rate
        wx, wy, wz = q.wx, q.wy, q.wz
        tx = ixx * kr * (wdx - wx) + (izz - iyy) * wy * wz
        ty = iyy * kr * (wdy - wy) + (ixx - izz) * wz * wx
        tz = izz * kr * (wdz - wz) + (iyy - ixx) * wx * wy
        thrust = self.params.mass_kg * (fx * r02 + fy * r12 + fz * r22)
        thrust = 0.0 if thrust < 0.0 else thrust
        thrust = self._max_thrust if self._max_thrust < thrust else thrust
        a_, k_, f_max = self._mixer
        return mix_with(a_, k_, f_max, thrust, tx, ty, tz)


# Setpoint generators: what the modes above the controller feed it.

BRAKED_SPEED_M_S = 0.1  # a centred stick latches the position once the drone is this slow
YAW_FOLLOW_MIN_SPEED_M_S = 0.2  # a route slower than this does not turn the drone's heading


def wrap_angle(angle: float) -> float:
    """Angle in [-pi, pi)."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


def fly_sticks(
    q: Quadrotor,
    sp: Setpoint,
    sticks: tuple[float, float, float, float],
    limits: ControlLimits,
    dt: float,
) -> None:
    """Angle-mode sticks ``(throttle, yaw, pitch, roll)``, each in -1..1 and already zero where
    centred, as a setpoint: climb rate, yaw rate (positive counter-clockwise from above),
    forward and rightward speed, each a fraction of its limit. A centred axis brakes to a stop,
    then holds the position where it stopped."""
    throttle, yaw, pitch, roll = sticks
    sp.yaw_rate = yaw * limits.max_yaw_rate_rad_s
    sp.yaw = wrap_angle(sp.yaw + sp.yaw_rate * dt)
    sp.ax = sp.ay = sp.az = 0.0
    if pitch or roll:
        forward, right = pitch * limits.max_speed_m_s, roll * limits.max_speed_m_s
        c, s = math.cos(sp.yaw), math.sin(sp.yaw)
        sp.hold_xy, sp.vx, sp.vy = False, forward * c + right * s, forward * s - right * c
    elif not sp.hold_xy:
        sp.vx = sp.vy = 0.0
        if math.hypot(q.vx, q.vy) < BRAKED_SPEED_M_S:
            sp.hold_xy, sp.x, sp.y = True, q.px, q.py
    if throttle:
        sp.hold_z, sp.vz = False, throttle * limits.max_climb_rate_m_s
    elif not sp.hold_z:
        sp.vz = 0.0
        if abs(q.vz) < BRAKED_SPEED_M_S:
            sp.hold_z, sp.z = True, q.pz


class RouteTracker:
    """Feeds a timed route (``duration_s``, ``sample(times) -> (pos, vel, acc)``) to the
    controller: position with velocity and acceleration feed-forward, heading along the travel.

    The route is sampled once at the physics rate, so a step costs a lookup, not numpy calls.
    Its clock ``t_s`` slows down, then stops, while the drone lags more than half of, then all
    of ``max_lag_m`` behind the setpoint (feed-forward scaled to match), so that a drone held
    back never cuts corners to catch up.
    """

    def __init__(
        self, route: Route, dt: float, max_lag_m: float, max_yaw_rate_rad_s: float
    ) -> None:
        self.route = route
        self.dt = dt
        self.t_s = 0.0
        self.duration_s = float(route.duration_s)
        self._max_lag = max_lag_m
        self._max_turn = max_yaw_rate_rad_s * dt
        times = np.arange(math.ceil(self.duration_s / dt) + 2) * dt
        self._table = np.hstack(route.sample(times)).tolist()

    @property
    def finished(self) -> bool:
        """The clock reached the end of the route (the drone may still be settling)."""
        return self.t_s >= self.duration_s

    def update(self, q: Quadrotor, sp: Setpoint) -> None:
        """Advance the clock one step and write the setpoint."""
        lag = math.dist((q.px, q.py, q.pz), (sp.x, sp.y, sp.z))
        rate = 2.0 - 2.0 * lag / self._max_lag
        rate = rate if rate > 0.0 else 0.0  # min(1, max(0, rate)), as comparisons
        rate = rate if rate < 1.0 else 1.0
        t = self.t_s + rate * self.dt
        t = self.duration_s if self.duration_s < t else t
        self.t_s = t
        u = t / self.dt
        i = int(u)
        f = u - i
        x0, y0, z0, vx0, vy0, vz0, ax0, ay0, az0 = self._table[i]
        x1, y1, z1, vx1, vy1, vz1, ax1, ay1, az1 = self._table[i + 1]
        x, y, z = x0 + f * (x1 - x0), y0 + f * (y1 - y0), z0 + f * (z1 - z0)
        vx, vy, vz = vx0 + f * (vx1 - vx0), vy0 + f * (vy1 - vy0), vz0 + f * (vz1 - vz0)
        ax, ay, az = ax0 + f * (ax1 - ax0), ay0 + f * (ay1 - ay0), az0 + f * (az1 - az0)
        r2 = rate * rate
        sp.hold_xy = sp.hold_z = True
        sp.x, sp.y, sp.z = x, y, z
        sp.vx, sp.vy, sp.vz = rate * vx, rate * vy, rate * vz
        sp.ax, sp.ay, sp.az = r2 * ax, r2 * ay, r2 * az
        if math.hypot(sp.vx, sp.vy) > YAW_FOLLOW_MIN_SPEED_M_S:
            turn = wrap_angle(math.atan2(sp.vy, sp.vx) - sp.yaw)
            turn = min(max(turn, -self._max_turn), self._max_turn)
            sp.yaw = wrap_angle(sp.yaw + turn)
            sp.yaw_rate = turn / self.dt
        else:
            sp.yaw_rate = 0.0

    def remaining(self, start: FloatArray) -> FloatArray:
        """``start`` (the setpoint) and the route's path samples still ahead: (N, 3)."""
        i = int(np.searchsorted(self.route.times, self.t_s, side="right"))
        return np.vstack([start, self.route.path[i:]])
