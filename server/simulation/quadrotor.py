"""Rigid-body quadrotor: four motors with first-order lag, linear drag and gravity.

Flight frame: metres, z up, gravity along -z. Body frame: x forward, y left, z up (thrust along
+z). Motors sit in an X at (+-a, +-a) in the body xy plane, a = arm / sqrt(2):

    0 front-left (+a, +a)  yaw torque +k f      1 front-right (+a, -a)  yaw torque -k f
    3 rear-left  (-a, +a)  yaw torque -k f      2 rear-right  (-a, -a)  yaw torque +k f

Integration is semi-implicit Euler at a fixed step (velocities first, then positions with the new
velocities); the attitude is a unit quaternion advanced by the exact rotation of the body rates
over the step and renormalised, so R stays orthonormal. Everything is plain float arithmetic:
numpy on 3-vectors costs microseconds per call, this step costs a few.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, fields

import numpy as np

from server.geometry.arrays import FloatArray
from server.simulation.config import SimulationConfig


@dataclass(frozen=True)
class QuadrotorParams:
    """Physical constants of the airframe (SI units)."""

    mass_kg: float
    inertia_kg_m2: tuple[float, float, float]
    arm_length_m: float
    yaw_moment_m: float  # reaction torque per newton of thrust
    motor_time_constant_s: float
    max_motor_thrust_n: float
    drag_n_s_m: float
    gravity_m_s2: float

    @classmethod
    def from_config(cls, config: SimulationConfig) -> QuadrotorParams:
        """The defaults live in SimulationConfig alone."""
        values = {f.name: getattr(config, f.name) for f in fields(cls)}
        return cls(**values | {"inertia_kg_m2": tuple(config.inertia_kg_m2)})

    @property
    def hover_thrust_n(self) -> float:
        """Per motor, N."""
        return self.mass_kg * self.gravity_m_s2 / 4.0


def mix(
    params: QuadrotorParams, thrust_n: float, tx: float, ty: float, tz: float
) -> tuple[float, float, float, float]:
    """Collective thrust (N) and body torques (N m) -> four motor thrusts within [0, max].

    When the motors cannot deliver everything, yaw torque is given up first, then the result is
    clipped (roll and pitch keep priority over yaw, as on real flight controllers).
    """
    return mix_with(
        params.arm_length_m / math.sqrt(2.0),
        params.yaw_moment_m,
        params.max_motor_thrust_n,
        thrust_n,
        tx,
        ty,
        tz,
    )


def mix_with(
    a: float, k: float, f_max: float, thrust_n: float, tx: float, ty: float, tz: float
) -> tuple[float, float, float, float]:
    """``mix`` with the airframe's constants worked out beforehand (the controllers call it at
    every physics step): ``a`` the motors' offset along body x and y (arm / sqrt 2, m), ``k``
    the yaw moment per newton (m), ``f_max`` a motor's full thrust (N). Same arithmetic; the
    clipping is written as comparisons, which return what min and max would."""
    base = 0.25 * thrust_n
    rx = 0.25 * tx / a
    ry = 0.25 * ty / a
    rz = 0.25 * tz / k
    f0 = base + rx - ry + rz
    f1 = base - rx - ry - rz
    f2 = base - rx + ry + rz
    f3 = base + rx + ry - rz
    if rz != 0.0 and (
        f0 < 0.0
        or f1 < 0.0
        or f2 < 0.0
        or f3 < 0.0
        or f0 > f_max
        or f1 > f_max
        or f2 > f_max
        or f3 > f_max
    ):
        # Largest share of the yaw command that keeps every motor within limits.
        scale = 1.0
        for f, s in ((f0, 1.0), (f1, -1.0), (f2, 1.0), (f3, -1.0)):
            without = f - s * rz
            if without == f:  # a yaw share too small to change this motor's thrust
                continue
            if f > f_max:
                scale = min(scale, max(0.0, (f_max - without) / (f - without)))
            elif f < 0.0:
                scale = min(scale, max(0.0, without / (without - f)))
        rz *= scale
        f0 = base + rx - ry + rz
        f1 = base - rx - ry - rz
        f2 = base - rx + ry + rz
        f3 = base + rx + ry - rz
    return (
        f_max if f0 > f_max else (0.0 if f0 < 0.0 else f0),
        f_max if f1 > f_max else (0.0 if f1 < 0.0 else f1),
        f_max if f2 > f_max else (0.0 if f2 < 0.0 else f2),
        f_max if f3 > f_max else (0.0 if f3 < 0.0 else f3),
    )


def quaternion_rotation(qw: float, qx: float, qy: float, qz: float) -> tuple[float, ...]:
    """The rotation of a unit quaternion (w, x, y, z) as 9 floats, row-major (plain floats:
    called at every physics step, where numpy's per-call cost would dominate)."""
    return (
        1 - 2 * (qy * qy + qz * qz),
        2 * (qx * qy - qw * qz),
        2 * (qx * qz + qw * qy),
        2 * (qx * qy + qw * qz),
        1 - 2 * (qx * qx + qz * qz),
        2 * (qy * qz - qw * qx),
        2 * (qx * qz - qw * qy),
        2 * (qy * qz + qw * qx),
        1 - 2 * (qx * qx + qy * qy),
    )


class Quadrotor:
    """State and fixed-step dynamics of one quadrotor.

    State (public float attributes, flight frame unless noted): position ``px, py, pz`` (m),
    velocity ``vx, vy, vz`` (m/s), attitude quaternion ``qw, qx, qy, qz`` (body to flight),
    body rates ``wx, wy, wz`` (rad/s, body frame) and motor thrusts ``f0..f3`` (N).
    """

    __slots__ = (
        "params",
        "dt",
        "px",
        "py",
        "pz",
        "vx",
        "vy",
        "vz",
        "qw",
        "qx",
        "qy",
        "qz",
        "wx",
        "wy",
        "wz",
        "f0",
        "f1",
        "f2",
        "f3",
        "_alpha",
        "_a",
        "_k",
        "_drag",
        "_ixx",
        "_iyy",
        "_izz",
        "_izz_iyy",
        "_ixx_izz",
        "_iyy_ixx",
        "_f_max",
        "_mass",
        "_gravity",
    )

    def __init__(self, params: QuadrotorParams, dt_s: float) -> None:
        self.params = params
        self.dt = float(dt_s)
        self._alpha = 1.0 - math.exp(-self.dt / params.motor_time_constant_s)  # exact lag step
        self._a = params.arm_length_m / math.sqrt(2.0)
        self._k = params.yaw_moment_m
        self._drag = params.drag_n_s_m / params.mass_kg
        self._ixx, self._iyy, self._izz = (float(i) for i in params.inertia_kg_m2)
        # Constants of the step, worked out once (the same values the step used to compute).
        self._izz_iyy = self._izz - self._iyy
        self._ixx_izz = self._ixx - self._izz
        self._iyy_ixx = self._iyy - self._ixx
        self._f_max = params.max_motor_thrust_n
        self._mass = params.mass_kg
        self._gravity = params.gravity_m_s2
        self.reset((0.0, 0.0, 0.0))

    def reset(self, position: Iterable[float], yaw_rad: float = 0.0, hovering: bool = True) -> None:
        """Level at ``position`` facing ``yaw_rad``, at rest; motors at hover thrust or off."""
        self.px, self.py, self.pz = (float(c) for c in position)
        self.vx = self.vy = self.vz = 0.0
        self.set_level(yaw_rad)
        f = self.params.hover_thrust_n if hovering else 0.0
        self.f0 = self.f1 = self.f2 = self.f3 = f

    def set_level(self, yaw_rad: float) -> None:
        """Attitude level with heading ``yaw_rad``, body rates zero."""
        self.qw, self.qx, self.qy, self.qz = (
            math.cos(0.5 * yaw_rad),
            0.0,
            0.0,
            math.sin(0.5 * yaw_rad),
        )
        self.wx = self.wy = self.wz = 0.0

    def step(self, c0: float, c1: float, c2: float, c3: float) -> None:
        """Advance one step with commanded motor thrusts ``c0..c3`` (N, clipped to [0, max])."""
        dt = self.dt
        f_max = self._f_max
        al = self._alpha
        # Motors: first-order lag towards the (saturated) commands.
        c0 = f_max if c0 > f_max else (0.0 if c0 < 0.0 else c0)
        c1 = f_max if c1 > f_max else (0.0 if c1 < 0.0 else c1)
        c2 = f_max if c2 > f_max else (0.0 if c2 < 0.0 else c2)
        c3 = f_max if c3 > f_max else (0.0 if c3 < 0.0 else c3)
        f0 = self.f0
        f0 += al * (c0 - f0)
        f1 = self.f1
        f1 += al * (c1 - f1)
        f2 = self.f2
        f2 += al * (c2 - f2)
        f3 = self.f3
        f3 += al * (c3 - f3)
        self.f0, self.f1, self.f2, self.f3 = f0, f1, f2, f3
        thrust = f0 + f1 + f2 + f3
        a = self._a
        tx = a * (f0 - f1 - f2 + f3)
        ty = a * (-f0 - f1 + f2 + f3)
        tz = self._k * (f0 - f1 + f2 - f3)

        # Translation: thrust along body z, gravity, linear drag.
        qw, qx, qy, qz = self.qw, self.qx, self.qy, self.qz
        t_m = thrust / self._mass
        drag = self._drag
        vx, vy, vz = self.vx, self.vy, self.vz
        vx += (t_m * 2.0 * (qx * qz + qw * qy) - drag * vx) * dt
        vy += (t_m * 2.0 * (qy * qz - qw * qx) - drag * vy) * dt
        vz += (t_m * (1.0 - 2.0 * (qx * qx + qy * qy)) - drag * vz - self._gravity) * dt
        self.vx, self.vy, self.vz = vx, vy, vz
        self.px += vx * dt
        self.py += vy * dt
        self.pz += vz * dt

        # Rotation: Euler's equations with diagonal inertia.
        ixx, iyy, izz = self._ixx, self._iyy, self._izz
        wx, wy, wz = self.wx, self.wy, self.wz
        wx += (tx - self._izz_iyy * wy * wz) / ixx * dt
        wy += (ty - self._ixx_izz * wz * wx) / iyy * dt
        wz += (tz - self._iyy_ixx * wx * wy) / izz * dt
        self.wx, self.wy, self.wz = wx, wy, wz

        # Attitude: q <- q * exp(w dt / 2), then renormalise.
        n = math.sqrt(wx * wx + wy * wy + wz * wz)
        if n > 1e-12:
            half = 0.5 * n * dt
            s = math.sin(half) / n
            dw, dx, dy, dz = math.cos(half), wx * s, wy * s, wz * s
            qw, qx, qy, qz = (
                qw * dw - qx * dx - qy * dy - qz * dz,
                qw * dx + qx * dw + qy * dz - qz * dy,
                qw * dy - qx * dz + qy * dw + qz * dx,
                qw * dz + qx * dy - qy * dx + qz * dw,
            )
            inv = 1.0 / math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
            self.qw, self.qx, self.qy, self.qz = qw * inv, qx * inv, qy * inv, qz * inv

    def state(self) -> tuple[float, ...]:
        """Position, velocity, quaternion, body rates and motor thrusts, for ``set_state``."""
        return (
            self.px,
            self.py,
            self.pz,
            self.vx,
            self.vy,
            self.vz,
            self.qw,
            self.qx,
            self.qy,
            self.qz,
            self.wx,
            self.wy,
            self.wz,
            self.f0,
            self.f1,
            self.f2,
            self.f3,
        )

    def set_state(self, state: tuple[float, ...]) -> None:
        (
            self.px,
            self.py,
            self.pz,
            self.vx,
            self.vy,
            self.vz,
            self.qw,
            self.qx,
            self.qy,
            self.qz,
            self.wx,
            self.wy,
            self.wz,
            self.f0,
            self.f1,
            self.f2,
            self.f3,
        ) = state

    def move_with_world(self, R: FloatArray, t: FloatArray, dyaw_rad: float) -> None:
        """Carry the drone with a corrected world (loop closure): ``R`` (3, 3), ``t`` (3,) m map
        old flight-frame points to new ones, and turn heading by ``dyaw_rad`` (R's yaw; the
        drone stays as level as it was). Position, velocity and attitude move; body rates and
        motors stay."""
        px, py, pz = R @ self.position + t
        vx, vy, vz = R @ self.velocity
        # Heading turns by dyaw about flight z: the yaw quaternion times the attitude.
        cw, sz = math.cos(0.5 * dyaw_rad), math.sin(0.5 * dyaw_rad)
        qw, qx, qy, qz = self.qw, self.qx, self.qy, self.qz
        self.px, self.py, self.pz = float(px), float(py), float(pz)
        self.vx, self.vy, self.vz = float(vx), float(vy), float(vz)
        self.qw, self.qx, self.qy, self.qz = (
            cw * qw - sz * qz,
            cw * qx - sz * qy,
            cw * qy + sz * qx,
            cw * qz + sz * qw,
        )

    # Read-outs (numpy, for callers outside the hot loop)

    def rotation(self) -> tuple[float, ...]:
        """R_flight_body as 9 floats, row-major."""
        return quaternion_rotation(self.qw, self.qx, self.qy, self.qz)

    @property
    def position(self) -> FloatArray:
        return np.array([self.px, self.py, self.pz])

    @property
    def velocity(self) -> FloatArray:
        return np.array([self.vx, self.vy, self.vz])

    @property
    def R_flight_body(self) -> FloatArray:
        return np.array(self.rotation()).reshape(3, 3)

    @property
    def T_flight_body(self) -> FloatArray:
        """4x4 body-to-flight transform, metres."""
        T = np.eye(4)
        T[:3, :3] = self.R_flight_body
        T[:3, 3] = (self.px, self.py, self.pz)
        return T

    @property
    def yaw_rad(self) -> float:
        """Heading of body x projected on the flight xy plane, counter-clockwise from +x."""
        qw, qx, qy, qz = self.qw, self.qx, self.qy, self.qz
        return math.atan2(2 * (qx * qy + qw * qz), 1 - 2 * (qy * qy + qz * qz))

    @property
    def tilt_rad(self) -> float:
        """Angle between body z and flight z."""
        return math.acos(min(1.0, max(-1.0, 1 - 2 * (self.qx * self.qx + self.qy * self.qy))))
