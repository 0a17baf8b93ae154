"""The drone's flight state and its modes: what each mode does at a physics step, and how modes
change (a command, an arrival, a touch of the map).

Flight frame (metres, z up; body x forward, y left, z up); simulation time in seconds since
spawn. Modes (drone_types.DroneMode): ``hover`` holds a setpoint, ``goto`` follows a route
(route_following.py), ``manual`` flies the sticks (manual_flight.py), ``landing`` sinks until
it touches down (``landed``: motors off, no physics), ``crashed`` falls with the motors off
until it rests on the map (``landed``). ``DroneModes`` is what contact.run_checked steps and
rewinds; a touch it reports is judged by contact.touch and turned into a mode here:

- a **crash** (``crash`` event): the route is dropped and the drone falls in mode ``crashed``;
- a **bump** (``collision`` event, at most one a second at one place): ``damage`` grows by
  ``bump_damage_per_m_s`` per m/s of normal speed, and a position the drone was holding moves
  ``planning_margin_m`` off the surface (a goto stops there);
- while landing, the touchdown; while crashed, coming to rest (``landed``).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from server.errors import DroneSimError
from server.geometry.arrays import FloatArray
from server.simulation.config import SimulationConfig
from server.simulation.contact import (
    CollisionReports,
    Touch,
    hold_off_surface,
    leave_obstacle,
    touch,
)
from server.simulation.control import (
    CascadedController,
    ControlGains,
    ControlLimits,
    RouteTracker,
    Setpoint,
)
from server.simulation.drone_types import DroneEvent, DroneEventKind, DroneMode
from server.simulation.flight_map import FlightMap
from server.simulation.manual_flight import ManualFlight
from server.simulation.other_drones import WithDrones
from server.simulation.quadrotor import Quadrotor, QuadrotorParams
from server.simulation.route import Route
from server.simulation.route_following import FollowerState, Replan, RouteFollower

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class _Saved:
    """What a physics step may change, for rewinding to before a contact."""

    quad: tuple[float, ...]
    setpoint: tuple[float | bool, ...]  # Setpoint's slots, in order
    mode: DroneMode | None
    route: FollowerState
    time_s: float
    n_events: int
    damage: float
    pilot: tuple[object, ...] = ()  # PilotController.state()


class DroneModes:
    """One drone's flight state (quadrotor, setpoint, mode, route, manual flight, time, events)
    and its mode changes; ``DroneSimulator`` (drone.py) drives it."""

    def __init__(self, config: SimulationConfig, flight_map: FlightMap) -> None:
        self.config = config
        self.flight_map = flight_map
        # What a touch is judged against: the map, with the room's other drones while the
        # simulator runs steps among them (drone.py, other_drones.py).
        self.contact_map: FlightMap | WithDrones = flight_map
        params = QuadrotorParams.from_config(config)
        self.quad = Quadrotor(params, config.dt_s)
        limits = ControlLimits.from_config(config)
        gains = ControlGains.from_config(config)
        self.ctrl = CascadedController(params, gains, limits)
        self.manual = ManualFlight(config, params, gains, limits)
        self.follower = RouteFollower(config, flight_map, limits.max_yaw_rate_rad_s)
        self.sp = Setpoint()
        self.mode: DroneMode | None = None  # None until spawned
        self.time_s = 0.0
        self.events: list[DroneEvent] = []
        self.command_id: int | None = None  # of the command the drone is carrying out
        self.collisions = CollisionReports()
        self.damage = 0.0  # bump damage points since spawn
        # The most acceleration the drone can have (m/s^2): all motors at full thrust, down.
        self.a_max = 4 * params.max_motor_thrust_n / params.mass_kg + params.gravity_m_s2

    # Physics steps (contact.Stepper: contact.run_checked drives them)

    def resting(self) -> bool:
        return self.mode == DroneMode.LANDED

    def wait(self, n: int) -> None:
        self.time_s += n * self.config.dt_s

    def save(self) -> _Saved:
        sp = self.sp
        return _Saved(
            self.quad.state(),
            tuple(getattr(sp, name) for name in Setpoint.__slots__),
            self.mode,
            self.follower.state(),
            self.time_s,
            len(self.events),
            self.damage,
            self.manual.pilot.state(),
        )

    def restore(self, saved: _Saved) -> None:
        self.mode = saved.mode
        self.follower.set_state(saved.route)
        self.time_s = saved.time_s
        self.damage = saved.damage
        self.quad.set_state(saved.quad)
        for name, value in zip(Setpoint.__slots__, saved.setpoint, strict=True):
            setattr(self.sp, name, value)
        del self.events[saved.n_events :]
        self.manual.pilot.set_state(saved.pilot)

    def step(self) -> None:
        """Mode logic, controller and one physics step."""
        mode = self.mode
        q = self.quad
        if mode == DroneMode.GOTO:
            tracker, goal = self.route()
            tracker.update(q, self.sp)
            if tracker.finished:
                self._check_arrival(goal)
        elif mode == DroneMode.MANUAL:
            motors = self.manual.motors(q, self.sp, self.time_s)
            if motors is not None:  # angle or acro
                q.step(*motors)
                self.time_s += q.dt
                return
        elif mode == DroneMode.CRASHED:
            q.step(0.0, 0.0, 0.0, 0.0)  # motors off: it falls
            self.time_s += q.dt
            return
        q.step(*self.ctrl.update(q, self.sp))
        self.time_s += q.dt

    def contact(self, last_free: FloatArray) -> None:
        """The step after ``last_free`` touched the map: a touchdown while landing, else what
        contact.touch judged it (module docstring)."""
        q = self.quad
        if self.mode == DroneMode.LANDING:
            q.reset(last_free, q.yaw_rad, hovering=False)
            self.hold(last_free)
            self.mode = DroneMode.LANDED
            self.emit(DroneEventKind.LANDED, "touched down, motors off")
            return
        hit = touch(q, self.contact_map, self.config, last_free, self.mode == DroneMode.CRASHED)
        if hit.kind == Touch.REST:
            self.sp.hold(last_free, q.yaw_rad)
            self.mode = DroneMode.LANDED
            self.emit(DroneEventKind.LANDED, "came to rest after the crash; take off to fly on")
        elif hit.kind == Touch.CRASH:
            self.follower.clear()
            self.mode = DroneMode.CRASHED
            self.emit(
                DroneEventKind.CRASH,
                f"crashed into the map at {hit.impact_m_s:.2f} m/s (crash speed "
                f"{self.config.crash_speed_m_s:.2f} m/s): motors off; take off again once it "
                "has landed",
            )
        elif hit.kind == Touch.BUMP:
            self._bumped(hit.position, hit.normal, hit.impact_m_s)

    def _bumped(self, where: FloatArray, normal: FloatArray, impact: float) -> None:
        """After a bump put the drone back at ``where``: damage, a setpoint off the surface
        (of unit ``normal``), and a ``collision`` event unless one was just told there."""
        cfg = self.config
        added = cfg.bump_damage_per_m_s * impact
        self.damage += added
        # A held position (or the goto's route) must not push it into the wall again.
        off = where + cfg.planning_margin_m * normal
        if self.mode == DroneMode.GOTO:
            self.hold(off)
        elif self.mode in (DroneMode.HOVER, DroneMode.MANUAL):
            hold_off_surface(self.sp, self.flight_map, off, cfg.planning_radius_m)
        if self.collisions.due(self.time_s, where):
            self.emit(
                DroneEventKind.COLLISION,
                f"bumped into the map at {impact:.2f} m/s (+{added:.1f} damage, "
                f"{self.damage:.0f} in all); bounced back",
            )

    # Mode changes

    def hold(self, position: Iterable[float]) -> None:
        """Hover at ``position``, facing where the drone faces."""
        self.follower.clear()
        self.mode = DroneMode.HOVER
        self.sp.hold(position, self.quad.yaw_rad)

    def start_route(self, route: Route) -> None:
        """Fly ``route`` (its goal set beforehand)."""
        self.follower.start(route, self.time_s)
        self.mode = DroneMode.GOTO

    def enter_manual(self) -> None:
        self.follower.clear()
        self.mode = DroneMode.MANUAL
        self.manual.take_over(self.quad, self.sp)

    def land(self) -> None:
        """Sink straight down until touching the map."""
        self.follower.clear()
        self.mode = DroneMode.LANDING
        self.sp.descend(self.quad.px, self.quad.py, self.config.landing_speed_m_s)

    def act_on(self, replan: Replan) -> None:
        """Fly the goto's new route (``replanned``), or hold where there is none
        (``blocked``)."""
        if replan.route is None:
            self.hold(self.quad.position)  # forgets the goal; the event keeps it
            self.emit(DroneEventKind.BLOCKED, replan.message, point=replan.point)
        else:
            self.start_route(replan.route)
            self.emit(DroneEventKind.REPLANNED, replan.message, point=replan.point)

    def leave_obstacle(self) -> None:
        """If the map grew into the drone, move it to the nearest free point (a collision)."""
        if leave_obstacle(self.quad, self.flight_map, self.config):
            self.hold(self.quad.position)
            self.emit(DroneEventKind.COLLISION, "the map grew into the drone; moved it out")

    def _check_arrival(self, goal: FloatArray) -> None:
        q, cfg = self.quad, self.config
        near = math.dist((q.px, q.py, q.pz), goal) <= cfg.arrival_tolerance_m
        slow = math.sqrt(q.vx * q.vx + q.vy * q.vy + q.vz * q.vz) <= cfg.arrival_speed_m_s
        if near and slow:
            self.hold(goal)
            self.emit(DroneEventKind.ARRIVED, "arrived at {point}", point=goal)

    # Read-outs

    def route(self) -> tuple[RouteTracker, FloatArray]:
        """The tracker and goal of the goto in progress: both are set exactly while in GOTO
        mode (``start_route``, cleared with the route), so a miss is a bug here."""
        tracker, goal = self.follower.tracker, self.follower.goal
        if tracker is None or goal is None:
            raise DroneSimError(f"no route to follow in mode {self.mode}")
        return tracker, goal

    def setpoint(self) -> FloatArray:
        """(3,) the position the controller is headed for, m."""
        return np.array([self.sp.x, self.sp.y, self.sp.z])

    def emit(self, kind: DroneEventKind, message: str, point: np.ndarray | None = None) -> None:
        """message: text without coordinates; ``{point}`` in it stands for ``point``."""
        point = None if point is None else np.array(point, dtype=np.float64)
        event = DroneEvent(kind, self.time_s, self.quad.position, message, self.command_id, point)
        log.debug("drone event %s at %.2f s: %s", kind.value, self.time_s, message)
        self.events.append(event)

    def take_events(self) -> list[DroneEvent]:
        """The events since the last call, oldest first."""
        events, self.events = self.events, []
        return events
