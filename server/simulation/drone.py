"""One session's virtual drone: modes, pilot commands, route following, collisions, events.

Everything is in the gravity-aligned flight frame (metres, z up; body x forward, y left, z up).
Time is simulation time in seconds since the drone spawned; ``advance(dt)`` moves it on by fixed
physics steps (the remainder carries over to the next call).

Collisions are checked at every physics step: the drone is a sphere of ``radius_m`` and touches
the map when the distance field at its centre drops below the radius. The distance field is
1-Lipschitz, so a chunk of steps whose travelled length is provably shorter than the clearance
at its start needs no query per step; near obstacles a few steps are run and every one of them
is checked in one query, rewinding to the step before a contact. A step moves at most
max_speed / physics_hz (< radius, checked by the config), so the sphere cannot jump over a wall
between two checks (the swept segment is covered), and ``segments_free`` guards longer steps.

A contact is judged by its speed along the surface normal (the distance field's gradient where
the drone touched): at ``crash_speed_m_s`` or more it is a **crash** (``crash`` event; motors
off, the drone tumbles down in mode ``crashed`` until it rests on the map, ``landed``, and the
pilot takes off again); below it a **bump** (``collision`` event, at most one a second at one
place): the drone goes back to its last collision-free position with its normal velocity
reflected (times ``bump_restitution``) and its speed along the surface damped (``bump_friction``),
``damage`` grows by ``bump_damage_per_m_s`` per m/s of normal speed, and a position it was
holding moves ``planning_margin_m`` off the surface (a goto stops there). While landing, contact
is the touchdown instead.

Commands come from one thread and ``advance`` from another: a lock guards the state.
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from enum import Enum

import numpy as np
from numpy.typing import ArrayLike

from server.errors import DroneSimError
from server.geometry.arrays import BoolArray, FloatArray, IndexArray
from server.simulation.config import SimulationConfig
from server.simulation.control import (
    CascadedController,
    ControlGains,
    ControlLimits,
    RouteTracker,
    Setpoint,
    fly_sticks,
)
from server.simulation.flight_map import Box, FlightMap, Region
from server.simulation.pilot_modes import (
    FlightMode,
    PilotController,
    StickRates,
    hand_over_to_position,
)
from server.simulation.planner import PlanningError, Route, plan_path, route_is_clear
from server.simulation.polyline import simplify
from server.simulation.quadrotor import Quadrotor, QuadrotorParams

log = logging.getLogger(__name__)

LIPSCHITZ_SAFETY = 1.5  # the interpolated distance field may change faster than 1 m per metre
MAX_CHUNK_STEPS = 100  # physics steps between distance queries far from obstacles
NEAR_CHUNK_STEPS = 16  # near obstacles, steps checked together in one query
# A drone pushed against a wall touches it again and again: one collision event per second
# at the same place (the stop itself happens every time).
COLLISION_REPEAT_S = 1.0
COLLISION_REPEAT_M = 0.05
BUMP_STANDOFF_M = 0.01  # a bump puts the drone this far off the surface (resting contacts)
CRASH_TUMBLE_RAD_S = 4.0  # a crashed drone tumbles at this rate while it falls
CRASH_REST_NORMAL_Z = 0.5  # a crashed drone rests on a surface whose normal is this far up
CRASH_REST_SPEED_M_S = 0.3  # ... or on any surface once slower than this
ROUTE_CLIMB_SHARE = 0.7  # routes climb and descend at this share of max_climb_rate_m_s
# The status's route is the path's corners: straight lines between them stay this close to the
# smoothed path (m), well under the drone's radius, with a few points instead of hundreds.
ROUTE_TOLERANCE_M = 0.02


class DroneMode(str, Enum):
    """Flight modes, named as in the protocol's drone_state.mode."""

    LANDED = "landed"
    HOVER = "hover"
    MANUAL = "manual"
    GOTO = "goto"
    LANDING = "landing"
    CRASHED = "crashed"  # motors off after a crash, falling until it rests on the map


class DroneEventKind(str, Enum):
    """Kinds of drone_event."""

    SPAWNED = "spawned"
    COLLISION = "collision"
    ARRIVED = "arrived"
    REPLANNED = "replanned"
    BLOCKED = "blocked"
    LANDED = "landed"
    CRASH = "crash"


class DroneCommandError(DroneSimError):
    """A command cannot be carried out now (no drone yet, wrong mode, bad input): bad_command."""


@dataclass(frozen=True)
class DroneEvent:
    """Something the pilot should hear about (the protocol's drone_event).

    ``message`` names no coordinates itself: where it mentions a point it holds ``{point}``
    and ``point`` is that point (flight frame, m). The simulator cannot say where the point is
    in the pilot's frame; ``text`` writes it in whichever frame the caller maps it to."""

    kind: DroneEventKind
    time_s: float  # simulation time
    position: FloatArray  # (3,) flight frame, m
    message: str
    command_id: int | None = None
    point: np.ndarray | None = None  # (3,) flight frame, m: the ``{point}`` of the message

    def text(self, to_frame: Callable[[FloatArray], ArrayLike] = lambda p: p) -> str:
        """The message with ``{point}`` written as ``(x, y, z) m`` after ``to_frame`` (a map
        from flight-frame points to the reader's frame; identity by default)."""
        if self.point is None:
            return self.message
        x, y, z = np.asarray(to_frame(self.point), dtype=np.float64)
        return self.message.format(point=f"({x:.2f}, {y:.2f}, {z:.2f}) m")


@dataclass(frozen=True)
class DroneStatus:
    """The drone's state for drone_state, in the flight frame (the server maps it to world)."""

    time_s: float  # simulation time since spawn, s
    T_flight_drone: FloatArray  # (4, 4) body to flight frame, m
    velocity: FloatArray  # (3,) flight frame, m/s
    mode: DroneMode
    clearance: float  # distance field at the centre, m
    target: FloatArray | None  # (3,) goto target
    # (N, 3) the remaining route's corners: the setpoint, then the vertices of the path ahead
    # (within ROUTE_TOLERANCE_M of it when drawn straight), N <= max_route_points; goto only
    route: FloatArray | None
    command_id: int | None
    flight_mode: FlightMode = FlightMode.POSITION  # how sticks fly the drone (pilot_modes.py)
    damage: float = 0.0  # damage points from bumps since spawn


@dataclass(frozen=True)
class _Saved:
    """What a physics step may change, for rewinding to before a contact."""

    quad: tuple[float, ...]
    setpoint: tuple[float | bool, ...]  # Setpoint's slots, in order
    mode: DroneMode | None
    tracker: RouteTracker | None
    tracker_t_s: float
    goal: FloatArray | None
    time_s: float
    n_events: int
    damage: float
    replan: Callable[[FloatArray], Route] | None
    pilot: tuple[object, ...] = ()  # PilotController.state()


def plan_route(
    flight_map: FlightMap,
    start: FloatArray,
    goal: FloatArray,
    config: SimulationConfig,
    speed_m_s: float,
) -> Route:
    """The route the drone flies from ``start`` to ``goal`` (flight frame, m) at up to
    ``speed_m_s``, with the drone's radius, margin and limits; raises PlanningError."""
    return plan_path(
        flight_map,
        start,
        goal,
        config.radius_m,
        margin_m=config.planning_margin_m,
        max_speed_m_s=speed_m_s,
        max_accel_m_s2=config.route_accel_m_s2,
        # Headroom below the controller's own limit, so it can catch up at the
        # end of a descent instead of overshooting into the floor.
        max_climb_rate_m_s=ROUTE_CLIMB_SHARE * config.max_climb_rate_m_s,
    )


class DroneSimulator:
    """The virtual quadrotor of one session, flying in ``flight_map``."""

    def __init__(self, config: SimulationConfig, flight_map: FlightMap) -> None:
        self.config = config
        self.flight_map = flight_map
        params = QuadrotorParams.from_config(config)
        self._quad = Quadrotor(params, config.dt_s)
        self._limits = ControlLimits.from_config(config)
        gains = ControlGains.from_config(config)
        self._ctrl = CascadedController(params, gains, self._limits)
        self._pilot = PilotController(params, gains, StickRates.from_config(config))
        self._flight_mode = FlightMode.POSITION
        self._sp = Setpoint()
        self._lock = threading.RLock()
        self._mode: DroneMode | None = None  # None until spawned
        self._time_s = 0.0
        self._carry_s = 0.0
        self._events: list[DroneEvent] = []
        self._command_id: int | None = None
        # goto
        self._tracker: RouteTracker | None = None
        self._corners: IndexArray = np.zeros(0, dtype=np.intp)  # indices into the route's path
        self._goal: FloatArray | None = None
        self._replan: Callable[[FloatArray], Route] | None = None  # command_route's planner
        self._speed = config.cruise_speed_m_s
        self._planned_at = 0.0
        # manual
        self._sticks: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
        self._sticks_at = -math.inf
        self._last_collision: tuple[float, FloatArray] = (-math.inf, np.zeros(3))  # time, position
        self.damage = 0.0  # bump damage points since spawn
        self._a_max = 4 * params.max_motor_thrust_n / params.mass_kg + params.gravity_m_s2

    # Commands

    def spawn(self, near: ArrayLike, yaw_rad: float = 0.0) -> FloatArray:
        """Appear hovering in observed free space as close to ``near`` as possible (within
        spawn_search_m); returns the position. Time restarts at 0; a ``spawned`` event follows."""
        point = self._point(near, "spawn point")
        with self._lock:
            free = self._nearest_free(point, self.config.planning_radius_m)
            if free is None or np.linalg.norm(free - point) > self.config.spawn_search_m:
                raise DroneCommandError(
                    f"no observed free space for the drone within {self.config.spawn_search_m} m "
                    f"of {np.round(point, 2).tolist()}"
                )
            position = free
            self._quad.reset(position, yaw_rad, hovering=True)
            self._hold(position)
            self._time_s = self._carry_s = 0.0
            self._last_collision = (-math.inf, np.zeros(3))
            self.damage = 0.0
            self._command_id = None
            self._emit(DroneEventKind.SPAWNED, "the drone is hovering, ready")
            return np.array(position)  # a copy

    def command_goto(
        self, target: ArrayLike, speed: float | None = None, command_id: int | None = None
    ) -> None:
        """Fly a planned route to ``target`` at ``speed`` (m/s, cruise speed when None).

        Raises PlanningError (with ``reason`` and ``nearest``) when there is no route; the drone
        then holds where it is.
        """
        goal = self._point(target, "goto target")
        with self._lock:
            self._require_flying("goto")
            speed = self.config.cruise_speed_m_s if speed is None else float(speed)
            if not math.isfinite(speed) or speed <= 0:
                raise DroneCommandError(f"goto speed must be a positive number, got {speed}")
            speed = min(speed, self.config.max_speed_m_s)
            self._command_id = command_id
            self._replan = None
            try:
                route = self._plan(goal, speed)
            except PlanningError:
                self._hold(self._quad.position)
                raise
            self._goal = goal
            self._speed = speed
            self._start_route(route)

    def command_route(
        self,
        route: Route,
        replan: Callable[[FloatArray], Route] | None = None,
        command_id: int | None = None,
    ) -> None:
        """Fly a route planned elsewhere (a course's autopilot: through its gates in order) as a
        goto to the route's end. When the map changes, ``replan(start)`` (flight frame) plans
        the rest anew from where the drone is, in place of a route straight to the end; it
        raises PlanningError when there is none (the drone then holds: ``blocked``)."""
        with self._lock:
            self._require_flying("a route")
            if len(route.path) == 0:
                raise DroneCommandError("an empty route")
            self._command_id = command_id
            self._goal = np.array(route.path[-1], dtype=float)
            self._replan = replan
            self._start_route(route)

    def command_sticks(
        self, sticks: ArrayLike, now_s: float | None = None, command_id: int | None = None
    ) -> None:
        """Manual flight: ``[throttle, yaw, pitch, roll]`` in -1..1; in position mode climb
        rate, yaw rate with positive counter-clockwise seen from above, forward speed, rightward
        speed, each a fraction of its limit (angle and acro: pilot_modes.py). ``now_s`` is
        when they were read, in simulation time (now when None); they count as centred once
        older than stick_timeout_s.

        Non-centred sticks take over from any flying mode; centred ones do not interrupt a goto
        or a landing. When landed, throttle above one half takes off into manual flight.
        """
        raw = np.asarray(sticks, dtype=float).reshape(-1)
        if raw.shape != (4,) or not np.all(np.isfinite(raw)):
            raise DroneCommandError("sticks must be 4 finite numbers [throttle, yaw, pitch, roll]")
        dz = self.config.stick_deadband  # applied once here, not on every physics step
        throttle, yaw, pitch, roll = (
            0.0 if abs(v) <= dz else float(v) for v in np.clip(raw, -1.0, 1.0)
        )
        values = (throttle, yaw, pitch, roll)
        with self._lock:
            self._require_spawned()
            self._sticks = values
            self._sticks_at = self._time_s if now_s is None else float(now_s)
            active = any(values)
            if self._mode == DroneMode.CRASHED:
                return  # falling with the motors off: nothing to steer until it has landed
            if self._mode == DroneMode.LANDED:
                if values[0] <= 0.5:  # throttle
                    return
                self._quad.reset(self._quad.position, self._quad.yaw_rad, hovering=True)
            elif self._mode != DroneMode.MANUAL and not active:
                return
            if self._mode != DroneMode.MANUAL:
                self._enter_manual()
            self._command_id = command_id

    def set_flight_mode(self, mode: str, command_id: int | None = None) -> None:
        """How the sticks fly the drone from now on: ``position`` (the default: velocities,
        centred holds position), ``angle`` (self-levelling: tilt and yaw rate) or ``acro``
        (body rates); pilot_modes.py says what each stick means. Allowed at any time, before
        spawn too; takes effect in manual flight (mid-flight without a jump: the new mode starts
        from the drone's attitude). An unknown mode raises DroneCommandError and changes
        nothing."""
        try:
            new = FlightMode(mode)
        except ValueError:
            choices = ", ".join(m.value for m in FlightMode)
            raise DroneCommandError(f"flight_mode must be one of {choices}; got {mode!r}") from None
        with self._lock:
            self._flight_mode = new
            if self._mode is not None:
                self._command_id = command_id

    def command_hold(self, command_id: int | None = None) -> None:
        """Stop and hover where the drone is."""
        with self._lock:
            self._require_flying("hold")
            self._command_id = command_id
            self._hold(self._quad.position)

    def command_land(self, command_id: int | None = None) -> None:
        """Descend straight down until touching the map, then stop the motors (``landed``)."""
        with self._lock:
            self._require_spawned()
            self._command_id = command_id
            if self._mode in (DroneMode.LANDED, DroneMode.LANDING, DroneMode.CRASHED):
                return
            self._clear_route()
            self._mode = DroneMode.LANDING
            sp = self._sp
            sp.x, sp.y, sp.vx, sp.vy, sp.ax, sp.ay, sp.az = (
                self._quad.px,
                self._quad.py,
                0.0,
                0.0,
                0.0,
                0.0,
                0.0,
            )
            sp.hold_xy, sp.hold_z, sp.yaw_rate = True, False, 0.0
            sp.vz = -self.config.landing_speed_m_s

    def command_takeoff(self, command_id: int | None = None) -> None:
        """From landed: rise up to takeoff_height_m (less where the map is lower) and hover."""
        with self._lock:
            mode = self._require_spawned()
            if mode != DroneMode.LANDED:
                raise DroneCommandError(f"takeoff needs a landed drone; it is {mode.value}")
            start = self._quad.position
            step = self.config.voxel_m / 2
            heights = np.arange(step, self.config.takeoff_height_m + 1e-9, step)
            clear = self.flight_map.distance(start + heights[:, None] * [0.0, 0.0, 1.0])
            # Rise through sphere-free space; stop at the highest point with planning clearance.
            touching = clear < self.config.radius_m
            reachable = heights[: int(np.argmax(touching)) if touching.any() else len(heights)]
            good = reachable[clear[: len(reachable)] >= self.config.planning_radius_m]
            if len(good) == 0:
                raise DroneCommandError("no room above the drone to take off")
            self._command_id = command_id
            self._quad.reset(start, self._quad.yaw_rad, hovering=True)
            self._hold(start + [0.0, 0.0, good[-1]])

    # Map changes

    def update_map(
        self, origin: FloatArray, occupied: BoolArray, observed: BoolArray
    ) -> Box | None:
        """``flight_map.update`` and ``on_map_update`` under the simulator's lock, so that no
        physics step reads a half-replaced map; returns the changed box (or None)."""
        with self._lock:
            changed = self.flight_map.update(origin, occupied, observed)
            self.on_map_update(changed)
            return changed

    def update_map_region(self, region: Region) -> Box | None:
        """``flight_map.update_region`` (a sub-box, flight_map.Region) and ``on_map_update``
        under the simulator's lock; returns the changed box (or None)."""
        with self._lock:
            changed = self.flight_map.update_region(
                region.origin, region.occupied, region.observed, region.written
            )
            self.on_map_update(changed)
            return changed

    def on_map_update(self, changed_box: Box | None) -> None:
        """The flight map changed inside ``changed_box`` (the flight_map.Box that
        ``FlightMap.update`` and ``update_region`` return; None: nothing changed).

        Moves the drone out if the map grew into it; during a goto, replans when the remaining
        route is blocked (``replanned``, or ``blocked`` and hold), and at most every
        replan_min_interval_s when the change is near the route and a new route is clearly
        shorter.
        """
        if changed_box is None:
            return
        with self._lock:
            if self._mode is None or self._mode == DroneMode.LANDED:
                return
            self._leave_obstacle()
            if self._mode != DroneMode.GOTO:
                return
            tracker, goal = self._route()
            # The path samples lie a few centimetres apart: testing them is testing the path.
            remaining = tracker.remaining(self._setpoint())
            margin = self.config.replan_margin_m + self.config.planning_radius_m
            if not changed_box.contains(remaining, margin).any():
                return
            blocked = not route_is_clear(
                self.flight_map,
                tracker.route,
                self.config.radius_m,
                from_time_s=tracker.t_s,
            )
            if not blocked and self._time_s - self._planned_at < self.config.replan_min_interval_s:
                return
            try:
                route = self._plan(goal, self._speed)
            except PlanningError as exc:
                if blocked:
                    self._hold(self._quad.position)  # forgets self._goal; ``goal`` keeps it
                    # The planner's own text gives flight-frame coordinates: not for the pilot.
                    why = exc.reason.value.replace("_", " ")
                    self._emit(
                        DroneEventKind.BLOCKED,
                        f"no route any more to {{point}} ({why}); holding",
                        point=goal,
                    )
                return
            old = _polyline_length(remaining)
            if blocked or route.length_m < (1 - self.config.replan_min_gain) * old:
                self._start_route(route)
                why = "the route was blocked" if blocked else "a shorter route opened"
                self._emit(
                    DroneEventKind.REPLANNED,
                    f"{why}: new route {route.length_m:.2f} m (was {old:.2f} m to go)",
                )
            else:
                self._planned_at = self._time_s

    def move_with_world(
        self,
        T_delta: FloatArray,
        origin: FloatArray,
        occupied: BoolArray,
        observed: BoolArray,
    ) -> Box | None:
        """The map was rebuilt in a corrected world (a loop closure): ``T_delta`` (4x4, flight
        frame, metres) maps the old world's points into the new one. The new grid replaces the
        flight map, and the drone moves with its world so that it stays where it was relative to
        the room: position, velocity, heading (the yaw part of ``T_delta``; the drone stays
        level), the setpoint it holds and any goto target. A goto in flight is re-planned on the
        new map from the moved drone to the moved target (``replanned``), or held where no route
        is left (``blocked``); a route planned elsewhere (a course's autopilot, whose gates were
        laid in the old world) is not followed on: the drone holds (``blocked``). Returns the
        changed box as ``update_map`` does."""
        T = np.asarray(T_delta, dtype=np.float64)
        R, t = T[:3, :3], T[:3, 3]
        with self._lock:
            changed = self.flight_map.update(origin, occupied, observed)
            if self._mode is None:
                return changed
            dyaw = math.atan2(R[1, 0], R[0, 0])
            q = self._quad
            px, py, pz = R @ q.position + t
            vx, vy, vz = R @ q.velocity
            # Heading turns by dyaw about flight z: the yaw quaternion times the attitude.
            cw, sz = math.cos(0.5 * dyaw), math.sin(0.5 * dyaw)
            qw, qx, qy, qz = q.qw, q.qx, q.qy, q.qz
            state = list(q.state())
            state[0:3] = (float(px), float(py), float(pz))
            state[3:6] = (float(vx), float(vy), float(vz))
            state[6:10] = (
                cw * qw - sz * qz,
                cw * qx - sz * qy,
                cw * qy + sz * qx,
                cw * qz + sz * qw,
            )
            q.set_state(tuple(state))
            sp = self._sp
            sp.x, sp.y, sp.z = (float(c) for c in R @ [sp.x, sp.y, sp.z] + t)
            sp.vx, sp.vy, sp.vz = (float(c) for c in R @ [sp.vx, sp.vy, sp.vz])
            sp.ax, sp.ay, sp.az = (float(c) for c in R @ [sp.ax, sp.ay, sp.az])
            sp.yaw += dyaw
            self._last_collision = (self._last_collision[0], R @ self._last_collision[1] + t)
            if self._mode == DroneMode.GOTO:
                _, goal = self._route()
                goal = R @ goal + t
                if self._replan is not None:
                    self._hold(q.position)
                    self._emit(
                        DroneEventKind.BLOCKED,
                        "the map was corrected (loop closure): the course's route is left; holding",
                    )
                else:
                    try:
                        route = self._plan(goal, self._speed)
                    except PlanningError as exc:
                        self._hold(q.position)
                        why = exc.reason.value.replace("_", " ")
                        self._emit(
                            DroneEventKind.BLOCKED,
                            f"the map was corrected (loop closure) and no route is left to "
                            f"{{point}} ({why}); holding",
                            point=goal,
                        )
                    else:
                        self._goal = goal
                        self._start_route(route)
                        self._emit(
                            DroneEventKind.REPLANNED,
                            f"the map was corrected (loop closure): new route "
                            f"{route.length_m:.2f} m to {{point}}",
                            point=goal,
                        )
            if self._mode != DroneMode.LANDED:
                self._leave_obstacle()
            return changed

    # Simulation

    def advance(self, dt_s: float) -> list[DroneEvent]:
        """Run the physics for ``dt_s`` seconds of simulated time (whole steps; the rest carries
        over); returns the events since the last call, oldest first."""
        with self._lock:
            if self._mode is not None and dt_s > 0:
                span = self._carry_s + dt_s
                if span > self.config.max_advance_s:
                    log.warning("advance(%.3f s) capped at %.3f s", dt_s, self.config.max_advance_s)
                    span = self.config.max_advance_s
                n = int(span * self.config.physics_hz + 1e-9)
                self._carry_s = span - n * self.config.dt_s
                self._run(n)
            events, self._events = self._events, []
            return events

    def status(self) -> DroneStatus:
        """The drone's state now; raises DroneCommandError before spawn."""
        with self._lock:
            mode = self._require_spawned()
            q = self._quad
            position = q.position
            target = route = None
            if mode == DroneMode.GOTO:
                tracker, goal = self._route()
                target, route = goal.copy(), self._remaining_route(tracker)
            return DroneStatus(
                time_s=self._time_s,
                T_flight_drone=q.T_flight_body,
                velocity=q.velocity,
                mode=mode,
                clearance=float(self.flight_map.distance(position[None])[0]),
                target=target,
                route=route,
                command_id=self._command_id,
                flight_mode=self._flight_mode,
                damage=self.damage,
            )

    @property
    def spawned(self) -> bool:
        return self._mode is not None

    @property
    def mode(self) -> DroneMode | None:
        return self._mode

    @property
    def flight_mode(self) -> FlightMode:
        return self._flight_mode

    @property
    def time_s(self) -> float:
        return self._time_s

    # Physics loop with collision checks

    def _run(self, n: int) -> None:
        q = self._quad
        dt = self.config.dt_s
        radius = self.config.radius_m
        while n > 0:
            if self._mode == DroneMode.LANDED:
                self._time_s += n * dt
                return
            here = (q.px, q.py, q.pz)
            clearance = float(self.flight_map.distance(np.array([here]))[0])
            budget = (clearance - radius - self.config.voxel_m) / LIPSCHITZ_SAFETY
            if budget > 0:
                # Far from the map: steps whose travel |v| t + a_max t^2 / 2 stays within the
                # budget cannot touch it; no query needed.
                v = math.sqrt(q.vx * q.vx + q.vy * q.vy + q.vz * q.vz)
                t = (math.sqrt(v * v + 2 * self._a_max * budget) - v) / self._a_max
                k = min(n, MAX_CHUNK_STEPS, int(t / dt))
                if k > 0:
                    for _ in range(k):
                        self._step()
                    n -= k
                    continue
            # Near the map: run a few steps, then check each of them in one query; on contact,
            # rewind and replay up to the step before it (the simulation is deterministic).
            k = min(n, NEAR_CHUNK_STEPS)
            saved = self._save()
            track = [here]
            for _ in range(k):
                self._step()
                track.append((q.px, q.py, q.pz))
            j = self._first_contact(np.array(track))
            if j is None:
                n -= k
                continue
            self._restore(saved)
            for _ in range(j):
                self._step()
            self._time_s += dt  # the step that touched
            self._contact(np.array(track[j]))
            n -= j + 1

    def _first_contact(self, track: FloatArray) -> int | None:
        """Index of the first step of ``track`` ((k + 1, 3) positions) that touches the map, or
        None. Inside an obstacle (the map grew into the drone) it may move out, never deeper."""
        radius = self.config.radius_m
        d = self.flight_map.distance(track)
        touching = (d[1:] < radius) & (d[1:] < d[:-1])
        long = np.linalg.norm(np.diff(track, axis=0), axis=1) > 0.5 * radius
        if long.any():  # never at the configured limits; sweep such steps explicitly
            touching[long] |= ~self.flight_map.segments_free(
                track[:-1][long], track[1:][long], radius
            )
        return int(np.argmax(touching)) if touching.any() else None

    def _save(self) -> _Saved:
        """What a physics step may change, for ``_restore``."""
        sp = self._sp
        tracker = self._tracker
        return _Saved(
            self._quad.state(),
            tuple(getattr(sp, name) for name in Setpoint.__slots__),
            self._mode,
            tracker,
            tracker.t_s if tracker else 0.0,
            self._goal,
            self._time_s,
            len(self._events),
            self.damage,
            self._replan,
            self._pilot.state(),
        )

    def _restore(self, saved: _Saved) -> None:
        self._mode, self._tracker, self._goal = saved.mode, saved.tracker, saved.goal
        self._time_s = saved.time_s
        self.damage = saved.damage
        self._replan = saved.replan
        if self._tracker is not None:
            self._tracker.t_s = saved.tracker_t_s
        self._quad.set_state(saved.quad)
        for name, value in zip(Setpoint.__slots__, saved.setpoint, strict=True):
            setattr(self._sp, name, value)
        del self._events[saved.n_events :]
        self._pilot.set_state(saved.pilot)

    def _step(self) -> None:
        """Mode logic, controller and one physics step."""
        mode = self._mode
        q = self._quad
        if mode == DroneMode.GOTO:
            tracker, goal = self._route()
            tracker.update(q, self._sp)
            if tracker.finished:
                self._check_arrival(goal)
        elif mode == DroneMode.MANUAL:
            if self._by_attitude():
                q.step(*self._pilot.update(q, self._flight_mode, self._sticks))
                self._time_s += q.dt
                return
            fly_sticks(q, self._sp, self._current_sticks(), self._limits, q.dt)
        elif mode == DroneMode.CRASHED:
            q.step(0.0, 0.0, 0.0, 0.0)  # motors off: it falls
            self._time_s += q.dt
            return
        q.step(*self._ctrl.update(q, self._sp))
        self._time_s += q.dt

    def _contact(self, last_free: FloatArray) -> None:
        """The step after ``last_free`` touched the map: a touchdown while landing, else a crash
        or a bump by the speed along the surface normal (module docstring)."""
        q = self._quad
        yaw = q.yaw_rad
        if self._mode == DroneMode.LANDING:
            q.reset(last_free, yaw, hovering=False)
            self._hold(last_free)
            self._mode = DroneMode.LANDED
            self._emit(DroneEventKind.LANDED, "touched down, motors off")
            return
        v = np.array([q.vx, q.vy, q.vz])
        normal = self._surface_normal(last_free, v)
        v_n = float(v @ normal)  # negative: towards the surface
        impact = max(0.0, -v_n)
        if self._mode == DroneMode.CRASHED:
            self._crash_contact(last_free, v, normal, v_n)
            return
        if impact >= self.config.crash_speed_m_s:
            self._crash(last_free, v, normal, v_n, impact)
            return
        self._bump(last_free, v, normal, v_n, impact)

    def _surface_normal(self, where: FloatArray, v: FloatArray) -> FloatArray:
        """Unit normal of the map's surface nearest to ``where`` (the distance field's
        gradient, pointing away from it); against the velocity where the field is flat."""
        g = self.flight_map.gradient(where[None])[0]
        n = float(np.linalg.norm(g))
        if n > 1e-6:
            return np.asarray(g / n, dtype=float)
        speed = float(np.linalg.norm(v))
        return -v / speed if speed > 1e-9 else np.array([0.0, 0.0, 1.0])

    def _bump(
        self, last_free: FloatArray, v: FloatArray, normal: FloatArray, v_n: float, impact: float
    ) -> None:
        """Bounce: back to the last free position, normal velocity reflected and damped."""
        cfg, q = self.config, self._quad
        tangential = v - v_n * normal
        bounced = (1.0 - cfg.bump_friction) * tangential - cfg.bump_restitution * v_n * normal
        # A little off the surface, so that a drone pushed on against it (resting contact)
        # touches again after some steps, not at every one (each contact rewinds a chunk).
        off_surface = last_free + BUMP_STANDOFF_M * normal
        d_from, d_to = self.flight_map.distance(np.stack([last_free, off_surface]))
        if d_to > d_from:
            last_free = off_surface
        q.px, q.py, q.pz = (float(c) for c in last_free)
        q.vx, q.vy, q.vz = (float(c) for c in bounced)
        added = cfg.bump_damage_per_m_s * impact
        self.damage += added
        # A held position (or the goto's route) must not push it into the wall again.
        off = last_free + cfg.planning_margin_m * normal
        sp = self._sp
        if self._mode == DroneMode.GOTO:
            self._hold(off)
        elif self._mode in (DroneMode.HOVER, DroneMode.MANUAL):
            held = np.array([sp.x, sp.y, sp.z])
            if float(self.flight_map.distance(held[None])[0]) < cfg.planning_radius_m:
                if sp.hold_xy:
                    sp.x, sp.y = float(off[0]), float(off[1])
                if sp.hold_z:
                    sp.z = float(off[2])
        t_last, p_last = self._last_collision
        if (
            self._time_s - t_last > COLLISION_REPEAT_S
            or np.linalg.norm(last_free - p_last) > COLLISION_REPEAT_M
        ):
            self._emit(
                DroneEventKind.COLLISION,
                f"bumped into the map at {impact:.2f} m/s (+{added:.1f} damage, "
                f"{self.damage:.0f} in all); bounced back",
            )
            self._last_collision = (self._time_s, last_free)

    def _crash(
        self, last_free: FloatArray, v: FloatArray, normal: FloatArray, v_n: float, impact: float
    ) -> None:
        """Motors off at the last free position, a small bounce and a tumble: it falls."""
        q = self._quad
        self._clear_route()
        self._mode = DroneMode.CRASHED
        bounced = (v - v_n * normal) * (1.0 - self.config.bump_friction)
        bounced -= self.config.bump_restitution * v_n * normal
        q.px, q.py, q.pz = (float(c) for c in last_free)
        q.vx, q.vy, q.vz = (float(c) for c in bounced)
        q.f0 = q.f1 = q.f2 = q.f3 = 0.0
        # Tumble about the horizontal axis along the surface (body frame), a fixed rate.
        axis = np.cross([0.0, 0.0, 1.0], normal)
        if float(np.linalg.norm(axis)) < 1e-6:
            axis = np.array([1.0, 0.0, 0.0])
        axis = q.R_flight_body.T @ (axis / np.linalg.norm(axis))
        q.wx, q.wy, q.wz = (float(c) for c in CRASH_TUMBLE_RAD_S * axis)
        self._emit(
            DroneEventKind.CRASH,
            f"crashed into the map at {impact:.2f} m/s (crash speed "
            f"{self.config.crash_speed_m_s:.2f} m/s): motors off; take off again once it has "
            "landed",
        )

    def _crash_contact(
        self, last_free: FloatArray, v: FloatArray, normal: FloatArray, v_n: float
    ) -> None:
        """A crashed drone touches the map: it rests when that is ground below it or it is
        nearly still, else it slides off (normal velocity reflected and damped)."""
        q = self._quad
        if normal[2] >= CRASH_REST_NORMAL_Z or float(np.linalg.norm(v)) < CRASH_REST_SPEED_M_S:
            q.reset(last_free, q.yaw_rad, hovering=False)
            self._sp.hold(last_free, q.yaw_rad)
            self._mode = DroneMode.LANDED
            self._emit(DroneEventKind.LANDED, "came to rest after the crash; take off to fly on")
            return
        bounced = (v - v_n * normal) * (1.0 - self.config.bump_friction)
        bounced -= self.config.bump_restitution * v_n * normal
        q.px, q.py, q.pz = (float(c) for c in last_free)
        q.vx, q.vy, q.vz = (float(c) for c in bounced)

    def _leave_obstacle(self) -> None:
        """If the map grew into the drone, move it to the nearest free point (a collision)."""
        q = self._quad
        position = q.position
        if float(self.flight_map.distance(position[None])[0]) >= self.config.radius_m:
            return
        free = self._nearest_free(position, self.config.planning_radius_m)
        if free is None:
            log.warning("the map grew into the drone at %s and no free space is near", position)
            return
        q.reset(np.asarray(free, dtype=float), q.yaw_rad, hovering=True)
        self._hold(q.position)
        self._emit(DroneEventKind.COLLISION, "the map grew into the drone; moved it out")

    # Modes

    def _hold(self, position: Iterable[float]) -> None:
        self._clear_route()
        self._mode = DroneMode.HOVER
        self._sp.hold(position, self._quad.yaw_rad)

    def _clear_route(self) -> None:
        self._tracker = None
        self._goal = None
        self._replan = None

    def _require_spawned(self) -> DroneMode:
        """The mode; raises DroneCommandError before spawn."""
        if self._mode is None:
            raise DroneCommandError("no drone yet: it spawns with the first map")
        return self._mode

    def _route(self) -> tuple[RouteTracker, FloatArray]:
        """The tracker and goal of the goto in progress: both are set exactly while in GOTO
        mode (``_start_route``, cleared by ``_clear_route``), so a miss is a bug here."""
        if self._tracker is None or self._goal is None:
            raise DroneSimError(f"no route to follow in mode {self._mode}")
        return self._tracker, self._goal

    def _require_flying(self, what: str) -> None:
        self._require_spawned()
        if self._mode == DroneMode.LANDED:
            raise DroneCommandError(f"{what} needs a flying drone; it is landed (take off first)")
        if self._mode == DroneMode.CRASHED:
            raise DroneCommandError(
                f"{what} needs a flying drone; it crashed and is falling (take off again once "
                "it has landed)"
            )

    def _plan(self, goal: FloatArray, speed: float) -> Route:
        if self._replan is not None:
            return self._replan(self._quad.position)
        return plan_route(self.flight_map, self._quad.position, goal, self.config, speed)

    def _start_route(self, route: Route) -> None:
        cfg = self.config
        self._tracker = RouteTracker(
            route, cfg.dt_s, cfg.max_tracking_lag_m, self._limits.max_yaw_rate_rad_s
        )
        self._corners = simplify(route.path, ROUTE_TOLERANCE_M)  # once: the status is at 20 Hz
        self._planned_at = self._time_s
        self._mode = DroneMode.GOTO

    def _check_arrival(self, goal: FloatArray) -> None:
        q, cfg = self._quad, self.config
        near = math.dist((q.px, q.py, q.pz), goal) <= cfg.arrival_tolerance_m
        slow = math.sqrt(q.vx * q.vx + q.vy * q.vy + q.vz * q.vz) <= cfg.arrival_speed_m_s
        if near and slow:
            self._hold(goal)
            self._emit(DroneEventKind.ARRIVED, "arrived at {point}", point=goal)

    def _enter_manual(self) -> None:
        self._clear_route()
        self._mode = DroneMode.MANUAL
        self._sp.hold(self._quad.position, self._quad.yaw_rad)
        self._pilot.release()

    def _by_attitude(self) -> bool:
        """Whether angle or acro flies this manual step: so while the sticks are fresh. Stale
        sticks (a lost link) and a switch to position mode hand over to position mode's
        braking, then holding."""
        fresh = self._time_s - self._sticks_at <= self.config.stick_timeout_s
        if fresh and self._flight_mode != FlightMode.POSITION:
            return True
        if self._pilot.engaged:
            self._pilot.release()
            hand_over_to_position(self._sp, self._quad)
        return False

    def _current_sticks(self) -> tuple[float, float, float, float]:
        """The latest sticks (zero where centred: command_sticks applies the deadband), all zero
        once stale."""
        if self._time_s - self._sticks_at > self.config.stick_timeout_s:
            return (0.0, 0.0, 0.0, 0.0)
        return self._sticks

    # Helpers

    def _setpoint(self) -> FloatArray:
        return np.array([self._sp.x, self._sp.y, self._sp.z])

    def _remaining_route(self, tracker: RouteTracker) -> FloatArray:
        """The route ahead for the status: the setpoint, then the corners of the path ahead
        (every path sample ahead lies within ROUTE_TOLERANCE_M of the segments between them);
        thinned evenly (ends kept) to max_route_points in the unlikely case of more."""
        rest = tracker.remaining(self._setpoint())  # setpoint, then path[i:]
        path = tracker.route.path
        i = len(path) - (len(rest) - 1)
        ahead = self._corners[self._corners >= i]
        if len(ahead):
            # The setpoint lies between two corners: the stretch to the next one is simplified
            # anew, the corners after it hold as they are.
            head = rest[: ahead[0] - i + 2]
            rest = np.vstack([head[simplify(head, ROUTE_TOLERANCE_M)], path[ahead[1:]]])
        limit = self.config.max_route_points
        if len(rest) > limit:
            rest = rest[np.linspace(0, len(rest) - 1, limit).round().astype(int)]
        return rest

    def _nearest_free(self, point: FloatArray, radius_m: float) -> FloatArray | None:
        """``point`` itself when its clearance is ``radius_m`` or more, else the nearest free
        cell centre (None when there is none)."""
        if float(self.flight_map.distance(point[None])[0]) >= radius_m:
            return np.array(point)  # a copy
        free = self.flight_map.nearest_free(point, radius_m)
        return None if free is None else np.asarray(free, dtype=float)

    def _emit(self, kind: DroneEventKind, message: str, point: np.ndarray | None = None) -> None:
        """message: text without coordinates; ``{point}`` in it stands for ``point``."""
        q = self._quad
        point = None if point is None else np.array(point, dtype=np.float64)
        event = DroneEvent(kind, self._time_s, q.position, message, self._command_id, point)
        log.debug("drone event %s at %.2f s: %s", kind.value, self._time_s, message)
        self._events.append(event)

    @staticmethod
    def _point(value: ArrayLike, what: str) -> FloatArray:
        try:
            point = np.asarray(value, dtype=float).reshape(-1)
        except (TypeError, ValueError):
            point = np.empty(0)
        if point.shape != (3,) or not np.all(np.isfinite(point)):
            raise DroneCommandError(f"{what} must be 3 finite numbers, got {value!r}")
        return point


def _polyline_length(points: FloatArray) -> float:
    return float(np.linalg.norm(np.diff(points, axis=0), axis=1).sum())
