"""One session's virtual drone: pilot commands, map changes and physics, in that order of calls.

Everything is in the gravity-aligned flight frame (metres, z up; body x forward, y left, z up).
Time is simulation time in seconds since the drone spawned; ``advance(dt)`` moves it on by fixed
physics steps (the remainder carries over to the next call).

``DroneSimulator`` is the drone's one entry point; each part of the work has a module:

- commands.py checks a command's input and the mode it needs, before anything changes;
- modes.py holds the flight state and the modes: a step in each, and how they change;
- route_following.py flies a goto's route and decides what a map change means for it;
- contact.py checks every physics step against the map and judges a touch (bump or crash);
- manual_flight.py and pilot_modes.py fly the sticks, control.py the setpoints;
- stillness.py skips the steps while the drone holds still (a fixed point of the step).

Not thread-safe: one caller at a time. ``server.sessions.runtime.flight.Flight`` calls it only under
its lock, the one lock over the simulator and its map (commands come from one thread, ``advance``
from another).
"""

from __future__ import annotations

import logging
import math

import numpy as np
from numpy.typing import ArrayLike

from server.geometry.arrays import BoolArray, FloatArray
from server.simulation.commands import (
    checked_flight_mode,
    checked_point,
    checked_sticks,
    goto_speed,
    require_flying,
    require_spawned,
    takeoff_height,
)
from server.simulation.config import SimulationConfig
from server.simulation.contact import free_point_near, run_checked
from server.simulation.drone_types import (
    DroneCommandError,
    DroneEvent,
    DroneEventKind,
    DroneMode,
    DroneStatus,
)
from server.simulation.flight_map import FlightMap
from server.simulation.map_regions import Box, Region
from server.simulation.modes import DroneModes
from server.simulation.other_drones import WithDrones, clear_of_drones
from server.simulation.pilot_modes import FlightMode
from server.simulation.route import PlanningError, Route
from server.simulation.route_following import Replanner
from server.simulation.stillness import Stillness

log = logging.getLogger(__name__)


class DroneSimulator:
    """The virtual quadrotor of one session, flying in ``flight_map``."""

    def __init__(
        self, config: SimulationConfig, flight_map: FlightMap, skip_still: bool = True
    ) -> None:
        """``skip_still``: run no physics steps while the drone holds still (stillness.py);
        False steps every one of them, for comparisons."""
        self.config = config
        self.flight_map = flight_map
        self._modes = DroneModes(config, flight_map)
        # The room's other drones, (K, 3) flight frame (``set_others``): spheres to touch.
        self.other_centres = np.empty((0, 3))
        self._carry_s = 0.0  # simulated time short of a whole step, carried to the next advance
        self.stillness = Stillness(self._modes, flight_map, enabled=skip_still)

    # Commands

    def spawn(self, near: ArrayLike, yaw_rad: float = 0.0) -> FloatArray:
        """Appear hovering in observed free space as close to ``near`` as possible (within
        spawn_search_m), clear of the room's other drones (``set_others``); returns the
        position. Time restarts at 0; a ``spawned`` event follows."""
        m = self._modes
        free = self._hover_near(near, yaw_rad, "spawn point")
        m.time_s = self._carry_s = 0.0
        m.damage = 0.0
        m.emit(DroneEventKind.SPAWNED, "the drone is hovering, ready")
        return free

    def put_back(self, near: ArrayLike, yaw_rad: float, why: str) -> FloatArray:
        """Hover again in observed free space as close to ``near`` as possible, whatever the
        drone was doing (a race's restart after a crash: server/sessions/runtime/
        course_control.py). Unlike ``spawn`` the clock runs on and the damage stays; a
        ``restarted`` event (saying ``why``) follows. Returns the position."""
        free = self._hover_near(near, yaw_rad, "restart point")
        self._modes.emit(DroneEventKind.RESTARTED, why)
        return free

    def _hover_near(self, near: ArrayLike, yaw_rad: float, what: str) -> FloatArray:
        m = self._modes
        point = checked_point(near, what)
        free = free_point_near(self.flight_map, point, self.config.planning_radius_m)
        if free is not None and len(self.other_centres):  # not into a drone of the room
            free = clear_of_drones(
                self.flight_map, free, self.other_centres, self.config, self.config.spawn_search_m
            )
        if free is None or np.linalg.norm(free - point) > self.config.spawn_search_m:
            raise DroneCommandError(
                f"no observed free space for the drone within {self.config.spawn_search_m} m "
                f"of {np.round(point, 2).tolist()}"
            )
        m.quad.reset(free, yaw_rad, hovering=True)
        m.hold(free)
        m.collisions.reset()
        m.command_id = None
        return np.array(free)  # a copy

    def command_goto(
        self, target: ArrayLike, speed: float | None = None, command_id: int | None = None
    ) -> None:
        """Fly a planned route to ``target`` at ``speed`` (m/s, cruise speed when None).

        Raises PlanningError (with ``reason`` and ``nearest``) when there is no route; the drone
        then holds where it is.
        """
        m = self._modes
        goal = checked_point(target, "goto target")
        require_flying(m.mode, "goto")
        speed = goto_speed(speed, self.config)
        m.command_id = command_id
        m.follower.replan = None
        try:
            route = m.follower.plan(m.quad.position, goal, speed)
        except PlanningError:
            m.hold(m.quad.position)
            raise
        m.follower.goal = goal
        m.follower.speed = speed
        m.start_route(route)

    def command_route(
        self, route: Route, replan: Replanner | None = None, command_id: int | None = None
    ) -> None:
        """Fly a route planned elsewhere (a course's autopilot: through its gates in order) as a
        goto to the route's end. When the map changes, ``replan(start)`` (flight frame) plans
        the rest anew from where the drone is, in place of a route straight to the end; it
        raises PlanningError when there is none (the drone then holds: ``blocked``)."""
        m = self._modes
        require_flying(m.mode, "a route")
        if len(route.path) == 0:
            raise DroneCommandError("an empty route")
        m.command_id = command_id
        m.follower.goal = np.array(route.path[-1], dtype=float)
        m.follower.replan = replan
        m.start_route(route)

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
        m = self._modes
        values = checked_sticks(sticks, self.config.stick_deadband)
        require_spawned(m.mode)
        m.manual.set_sticks(values, m.time_s if now_s is None else float(now_s))
        if m.mode == DroneMode.CRASHED:
            return  # falling with the motors off: nothing to steer until it has landed
        if m.mode == DroneMode.LANDED:
            if values[0] <= 0.5:  # throttle
                return
            m.quad.reset(m.quad.position, m.quad.yaw_rad, hovering=True)
        elif m.mode != DroneMode.MANUAL and not any(values):
            return
        if m.mode != DroneMode.MANUAL:
            m.enter_manual()
        m.command_id = command_id

    def set_flight_mode(self, mode: str, command_id: int | None = None) -> None:
        """How the sticks fly the drone from now on: ``position`` (the default: velocities,
        centred holds position), ``angle`` (self-levelling: tilt and yaw rate) or ``acro``
        (body rates); pilot_modes.py says what each stick means. Allowed at any time, before
        spawn too; takes effect in manual flight (mid-flight without a jump: the new mode starts
        from the drone's attitude). An unknown mode raises DroneCommandError and changes
        nothing."""
        m = self._modes
        m.manual.flight_mode = checked_flight_mode(mode)
        if m.mode is not None:
            m.command_id = command_id

    def command_hold(self, command_id: int | None = None) -> None:
        """Stop and hover where the drone is."""
        m = self._modes
        require_flying(m.mode, "hold")
        m.command_id = command_id
        m.hold(m.quad.position)

    def command_land(self, command_id: int | None = None) -> None:
        """Descend straight down until touching the map, then stop the motors (``landed``)."""
        m = self._modes
        require_spawned(m.mode)
        m.command_id = command_id
        if m.mode not in (DroneMode.LANDED, DroneMode.LANDING, DroneMode.CRASHED):
            m.land()

    def command_takeoff(self, command_id: int | None = None) -> None:
        """From landed: rise up to takeoff_height_m (less where the map is lower) and hover."""
        m = self._modes
        mode = require_spawned(m.mode)
        if mode != DroneMode.LANDED:
            raise DroneCommandError(f"takeoff needs a landed drone; it is {mode.value}")
        start = m.quad.position
        height = takeoff_height(self.flight_map, start, self.config)
        m.command_id = command_id
        m.quad.reset(start, m.quad.yaw_rad, hovering=True)
        m.hold(start + [0.0, 0.0, height])

    # Map changes

    def update_map(
        self, origin: FloatArray, occupied: BoolArray, observed: BoolArray
    ) -> Box | None:
        """``flight_map.update`` and ``on_map_update`` in one call; returns the changed box
        (or None)."""
        changed = self.flight_map.update(origin, occupied, observed)
        self.on_map_update(changed)
        return changed

    def update_map_region(self, region: Region) -> Box | None:
        """``flight_map.update_region`` (a sub-box, flight_map.Region) and ``on_map_update``
        in one call; returns the changed box (or None)."""
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
        shorter (route_following.RouteFollower.after_map_change).
        """
        m = self._modes
        if changed_box is None or m.mode is None or m.mode == DroneMode.LANDED:
            return
        m.leave_obstacle()
        if m.mode != DroneMode.GOTO:
            return
        m.route()  # a goto has its route
        replan = m.follower.after_map_change(changed_box, m.setpoint(), m.quad.position, m.time_s)
        if replan is not None:
            m.act_on(replan)

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
        m = self._modes
        T = np.asarray(T_delta, dtype=np.float64)
        R, t = T[:3, :3], T[:3, 3]
        changed = self.flight_map.update(origin, occupied, observed)
        if m.mode is None:
            return changed
        dyaw = math.atan2(R[1, 0], R[0, 0])
        m.quad.move_with_world(R, t, dyaw)
        m.sp.move_with_world(R, t, dyaw)
        m.collisions.move_with_world(R, t)
        if m.mode == DroneMode.GOTO:
            m.route()  # a goto has its route
            m.act_on(m.follower.after_world_move(R, t, m.quad.position))
        if m.mode != DroneMode.LANDED:
            m.leave_obstacle()
        return changed

    # Simulation

    def advance(self, dt_s: float) -> list[DroneEvent]:
        """Run the physics for ``dt_s`` seconds of simulated time (whole steps; the rest carries
        over); returns the events since the last call, oldest first."""
        m = self._modes
        if m.mode is not None and dt_s > 0:
            span = self._carry_s + dt_s
            if span > self.config.max_advance_s:
                log.warning("advance(%.3f s) capped at %.3f s", dt_s, self.config.max_advance_s)
                span = self.config.max_advance_s
            n = int(span * self.config.physics_hz + 1e-9)
            self._carry_s = span - n * self.config.dt_s
            n = self.stillness.skip(n)  # none while the drone holds still
            if n > 0:
                contact_map: FlightMap | WithDrones = self.flight_map
                if len(self.other_centres):
                    contact_map = WithDrones(
                        self.flight_map, self.other_centres, self.config.radius_m
                    )
                m.contact_map = contact_map
                try:
                    run_checked(m, m.quad, contact_map, self.config, m.a_max, n)
                finally:
                    m.contact_map = self.flight_map
        return m.take_events()

    def set_others(self, centres: ArrayLike) -> None:
        """The other drones of a shared room, (K, 3) centres in the flight frame (metres),
        where they are now: spheres of this drone's radius that it bumps into or crashes on
        as on the map (other_drones.py), until the next call."""
        self.other_centres = np.asarray(centres, dtype=np.float64).reshape(-1, 3)

    def status(self) -> DroneStatus:
        """The drone's state now; raises DroneCommandError before spawn."""
        m = self._modes
        mode = require_spawned(m.mode)
        q = m.quad
        target = route = None
        if mode == DroneMode.GOTO:
            _, goal = m.route()
            target, route = goal.copy(), m.follower.remaining_route(m.setpoint())
        return DroneStatus(
            time_s=m.time_s,
            T_flight_drone=q.T_flight_body,
            velocity=q.velocity,
            mode=mode,
            clearance=self.flight_map.distance_at(q.px, q.py, q.pz),
            target=target,
            route=route,
            command_id=m.command_id,
            flight_mode=m.manual.flight_mode,
            damage=m.damage,
        )

    @property
    def spawned(self) -> bool:
        return self._modes.mode is not None

    @property
    def mode(self) -> DroneMode | None:
        return self._modes.mode

    @property
    def flight_mode(self) -> FlightMode:
        return self._modes.manual.flight_mode

    @property
    def time_s(self) -> float:
        return self._modes.time_s

    @property
    def damage(self) -> float:
        """Bump damage points since spawn."""
        return self._modes.damage
