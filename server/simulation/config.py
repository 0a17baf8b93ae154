"""Every parameter of the drone simulation in one place, with defaults and units.

All lengths are in metres, times in seconds, angles in degrees (converted where used), in the
gravity-aligned flight frame (z up). The defaults describe a small indoor quadrotor (500 g,
24 cm across, thrust-to-weight about 2.9).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

from server.errors import ConfigError

_MAY_BE_ZERO = {"stick_expo"}  # numeric settings that may be 0 (the others must be > 0)


@dataclass(frozen=True)
class SimulationConfig:
    """Physics, controller, limits and behaviour of one simulated drone."""

    # Integration
    physics_hz: int = 400  # fixed physics and control rate, Hz (>= 200)
    max_advance_s: float = 1.0  # longest simulated span per advance() call; more is dropped, s

    # Airframe
    radius_m: float = 0.12  # collision sphere around the centre of mass, m
    mass_kg: float = 0.5  # kg
    inertia_kg_m2: tuple[float, float, float] = (2.5e-3, 2.5e-3, 4.5e-3)  # diagonal, body x y z
    arm_length_m: float = 0.09  # centre to each motor (X layout), m
    yaw_moment_m: float = 0.016  # reaction torque per newton of thrust, N m / N
    motor_time_constant_s: float = 0.03  # first-order lag of each motor's thrust, s
    max_motor_thrust_n: float = 3.5  # per motor, N (4 motors)
    drag_n_s_m: float = 0.1  # linear drag, force per speed, N / (m/s)
    gravity_m_s2: float = 9.81  # m/s^2

    # Cascaded controller gains (each a bandwidth, 1/s)
    position_gain: float = 1.8  # position error -> velocity
    velocity_gain: float = 4.0  # velocity error -> acceleration
    attitude_gain: float = 9.0  # tilt error (rad) -> body rate (rad/s)
    yaw_gain: float = 3.0  # yaw error (rad) -> yaw rate (rad/s)
    rate_gain: float = 18.0  # body-rate error -> angular acceleration

    # Limits
    max_speed_m_s: float = 3.0  # horizontal, m/s
    max_climb_rate_m_s: float = 1.0  # vertical, up and down, m/s
    max_accel_m_s2: float = 4.0  # commanded acceleration (norm), m/s^2
    max_tilt_deg: float = 35.0  # body z against flight z, degrees
    max_yaw_rate_deg_s: float = 120.0  # degrees/s

    # Pilot flight modes angle and acro (server/simulation/pilot_modes.py); position mode uses
    # the limits above. A stick s in -1..1 is shaped by the cubic expo
    # (1 - stick_expo) s + stick_expo s^3 (0 linear; 0 and +-1 stay where they are).
    angle_max_deg: float = 40.0  # angle mode: tilt at full roll or pitch stick, degrees
    rate_roll_deg_s: float = 400.0  # acro: roll rate at full stick, deg/s; a limit in both modes
    rate_pitch_deg_s: float = 400.0  # acro: pitch rate at full stick, deg/s; likewise
    rate_yaw_deg_s: float = 200.0  # angle and acro: yaw rate at full stick, deg/s; likewise
    stick_expo: float = 0.3  # expo of the roll, pitch and yaw sticks in angle and acro, [0, 1)

    # Behaviour
    cruise_speed_m_s: float = 1.0  # goto speed when a command gives none, m/s
    route_accel_m_s2: float = 2.0  # acceleration limit the routes are timed with, m/s^2
    planning_margin_m: float = 0.08  # routes keep radius_m + this from obstacles, m
    takeoff_height_m: float = 1.0  # takeoff rises this far above where the drone landed, m
    spawn_search_m: float = 1.0  # spawn at most this far from the requested point, m
    landing_speed_m_s: float = 0.4  # descent rate while landing, m/s
    arrival_tolerance_m: float = 0.1  # goto ends when the drone is this close to the target, m
    arrival_speed_m_s: float = 0.3  # ... and slower than this, m/s
    max_tracking_lag_m: float = 0.4  # the route clock slows down when the drone lags this far, m
    stick_timeout_s: float = 0.5  # sticks older than this count as centred, s
    stick_deadband: float = 0.05  # |stick| below this counts as centred, fraction of full scale
    replan_margin_m: float = 0.3  # map changes closer than this to the remaining route replan, m
    replan_min_interval_s: float = 1.0  # voluntary replans (route still clear) at most this often
    replan_min_gain: float = 0.15  # a voluntary replan is kept if this fraction shorter
    standoff_m: float = 0.4  # pixel targets: fly to this far in front of the surface, m
    max_route_points: int = 512  # remaining route polyline in the status (protocol limit)

    # Flight map
    voxel_m: float = 0.05  # occupancy / distance-field cell, m
    unknown_is_free: bool = False  # plan and fly through unobserved space (dangerous)

    # Crashes and bumps (a contact's speed is its component along the surface normal)
    crash_speed_m_s: float = 1.5  # this fast or faster into the map is a crash: motors off, fall
    bump_restitution: float = 0.3  # a bump sends back this share of the normal speed
    bump_friction: float = 0.5  # ... and takes this share off the speed along the surface
    bump_damage_per_m_s: float = 10.0  # damage points a bump adds per m/s of normal speed

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            values = value if isinstance(value, tuple) else (value,)
            for v in values:
                numeric = isinstance(v, (int, float)) and not isinstance(v, bool)
                if numeric and not (math.isfinite(v) and (v > 0 or f.name in _MAY_BE_ZERO)):
                    raise ConfigError(f"simulation.{f.name} must be finite and > 0, got {value}")
        if self.physics_hz < 200:
            raise ConfigError(f"simulation.physics_hz must be >= 200, got {self.physics_hz}")
        if len(self.inertia_kg_m2) != 3:
            raise ConfigError("simulation.inertia_kg_m2 must hold 3 values (Ixx, Iyy, Izz)")
        if not 0 < self.max_tilt_deg < 80:
            raise ConfigError(
                f"simulation.max_tilt_deg must be in (0, 80), got {self.max_tilt_deg}"
            )
        hover_ratio = self.mass_kg * self.gravity_m_s2 / (4 * self.max_motor_thrust_n)
        if hover_ratio > 0.8:
            raise ConfigError(
                f"4 x max_motor_thrust_n = {4 * self.max_motor_thrust_n:.2f} N cannot lift "
                f"{self.mass_kg} kg with margin (hover needs {hover_ratio:.0%} of full thrust; "
                f"at most 80% allowed)"
            )
        if self.motor_time_constant_s < 2.0 / self.physics_hz:
            raise ConfigError("simulation.motor_time_constant_s must span at least 2 physics steps")
        if self.cruise_speed_m_s > self.max_speed_m_s:
            raise ConfigError(
                f"simulation.cruise_speed_m_s ({self.cruise_speed_m_s}) exceeds "
                f"max_speed_m_s ({self.max_speed_m_s})"
            )
        if self.route_accel_m_s2 > self.max_accel_m_s2:
            raise ConfigError(
                f"simulation.route_accel_m_s2 ({self.route_accel_m_s2}) exceeds "
                f"max_accel_m_s2 ({self.max_accel_m_s2})"
            )
        if not 0 < self.angle_max_deg < 80:
            raise ConfigError(
                f"simulation.angle_max_deg must be in (0, 80), got {self.angle_max_deg}"
            )
        if not 0 <= self.stick_expo < 1:
            raise ConfigError(f"simulation.stick_expo must be in [0, 1), got {self.stick_expo}")
        if self.stick_deadband >= 1:
            raise ConfigError("simulation.stick_deadband must be below 1")
        if self.replan_min_gain >= 1:
            raise ConfigError("simulation.replan_min_gain must be below 1")
        if self.radius_m < self.voxel_m:
            raise ConfigError(
                f"simulation.radius_m ({self.radius_m}) must be at least one voxel "
                f"({self.voxel_m}) so that the distance field can see contact"
            )
        for name in ("bump_restitution", "bump_friction"):
            if getattr(self, name) >= 1:
                raise ConfigError(f"simulation.{name} must be below 1, got {getattr(self, name)}")
        if self.max_speed_m_s / self.physics_hz > self.radius_m:
            raise ConfigError("one physics step at max_speed_m_s must move less than radius_m")

    @property
    def dt_s(self) -> float:
        """Physics step, s."""
        return 1.0 / self.physics_hz

    @property
    def planning_radius_m(self) -> float:
        """Clearance the planner keeps: the collision sphere plus a tracking margin, m."""
        return self.radius_m + self.planning_margin_m
