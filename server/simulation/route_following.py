"""A goto in progress: its route, the tracker that flies it, and planning it anew.

Flight frame, metres, z up; times are simulation time in seconds. ``plan_route`` plans with
the drone's radius, margin and limits. A ``RouteFollower`` holds the route being flown, its
goal and speed, and, for a route planned elsewhere (a course's autopilot), the planner that
plans the rest anew. When the map changes near the route ahead it decides what that means
(``after_map_change``): nothing, a new route (``replanned``: the old one is blocked, or one
clearly shorter opened), or none left (``blocked``); after a corrected world
(``after_world_move``) the route is planned again to the moved goal. The drone's modes
(modes.py: ``DroneModes.act_on``) act on the answer: they own the mode, the setpoint and the
events.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from server.errors import DroneSimError
from server.geometry.arrays import FloatArray, IndexArray
from server.simulation.config import SimulationConfig
from server.simulation.control import RouteTracker
from server.simulation.flight_map import FlightMap
from server.simulation.map_regions import Box
from server.simulation.planner import plan_path, route_is_clear
from server.simulation.polyline import simplify
from server.simulation.route import PlanningError, Route

ROUTE_CLIMB_SHARE = 0.7  # routes climb and descend at this share of max_climb_rate_m_s
# The status's route is the path's corners: straight lines between them stay this close to the
# smoothed path (m), well under the drone's radius, with a few points instead of hundreds.
ROUTE_TOLERANCE_M = 0.02

Replanner = Callable[[FloatArray], Route]  # start (3,), flight frame -> the rest of a route


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


def polyline_length(points: FloatArray) -> float:
    """Length (m) of the polyline through ``points`` (N, 3)."""
    return float(np.linalg.norm(np.diff(points, axis=0), axis=1).sum())


@dataclass(frozen=True)
class FollowerState:
    """What a physics step may change of a RouteFollower, for rewinding to before a contact."""

    tracker: RouteTracker | None
    tracker_t_s: float
    goal: FloatArray | None
    replan: Replanner | None


@dataclass(frozen=True)
class Replan:
    """What a change of the map means for the goto: ``route``, the new route to fly (None:
    none is left, the drone holds), and the event's ``message`` (``{point}``: ``point``)."""

    route: Route | None
    message: str
    point: FloatArray | None = None


class RouteFollower:
    """The route of the goto in progress (none outside goto: ``tracker`` and ``goal`` are set
    together by ``start`` and the goal beforehand, and cleared together by ``clear``)."""

    def __init__(
        self, config: SimulationConfig, flight_map: FlightMap, max_yaw_rate_rad_s: float
    ) -> None:
        self.config = config
        self.flight_map = flight_map
        self._max_yaw_rate = max_yaw_rate_rad_s
        self.tracker: RouteTracker | None = None
        self.goal: FloatArray | None = None
        self.replan: Replanner | None = None  # command_route's planner
        self.speed = config.cruise_speed_m_s  # m/s, what a goto's route is planned anew at
        self._corners: IndexArray = np.zeros(0, dtype=np.intp)  # indices into the route's path
        self._planned_at = 0.0  # simulation time the route was last planned or kept

    def plan(self, start: FloatArray, goal: FloatArray, speed: float) -> Route:
        """A route from ``start`` to ``goal``: the course's own planner when there is one;
        raises PlanningError."""
        if self.replan is not None:
            return self.replan(start)
        return plan_route(self.flight_map, start, goal, self.config, speed)

    def start(self, route: Route, time_s: float) -> None:
        """Fly ``route`` from now (``time_s``) on."""
        cfg = self.config
        self.tracker = RouteTracker(route, cfg.dt_s, cfg.max_tracking_lag_m, self._max_yaw_rate)
        self._corners = simplify(route.path, ROUTE_TOLERANCE_M)  # once: the status is at 20 Hz
        self._planned_at = time_s

    def clear(self) -> None:
        self.tracker = None
        self.goal = None
        self.replan = None

    def state(self) -> FollowerState:
        tracker = self.tracker
        return FollowerState(tracker, tracker.t_s if tracker else 0.0, self.goal, self.replan)

    def set_state(self, state: FollowerState) -> None:
        self.tracker, self.goal, self.replan = state.tracker, state.goal, state.replan
        if self.tracker is not None:
            self.tracker.t_s = state.tracker_t_s

    def _following(self) -> tuple[RouteTracker, FloatArray]:
        if self.tracker is None or self.goal is None:
            raise DroneSimError("no route is being followed")
        return self.tracker, self.goal

    def remaining_route(self, setpoint: FloatArray) -> FloatArray:
        """The route ahead for the status: the setpoint, then the corners of the path ahead
        (every path sample ahead lies within ROUTE_TOLERANCE_M of the segments between them);
        thinned evenly (ends kept) to max_route_points in the unlikely case of more."""
        tracker, _ = self._following()
        rest = tracker.remaining(setpoint)  # setpoint, then path[i:]
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

    def after_map_change(
        self, changed_box: Box, setpoint: FloatArray, position: FloatArray, time_s: float
    ) -> Replan | None:
        """The map changed inside ``changed_box`` while the drone at ``position`` follows the
        route from ``setpoint``: a new route when the route ahead is blocked (or none:
        ``Replan.route`` None), and at most every replan_min_interval_s when the change is
        near the route and a new route is clearly shorter; None: fly on."""
        cfg = self.config
        tracker, goal = self._following()
        # The path samples lie a few centimetres apart: testing them is testing the path.
        remaining = tracker.remaining(setpoint)
        margin = cfg.replan_margin_m + cfg.planning_radius_m
        if not changed_box.contains(remaining, margin).any():
            return None
        blocked = not route_is_clear(
            self.flight_map, tracker.route, cfg.radius_m, from_time_s=tracker.t_s
        )
        if not blocked and time_s - self._planned_at < cfg.replan_min_interval_s:
            return None
        try:
            route = self.plan(position, goal, self.speed)
        except PlanningError as exc:
            if not blocked:
                return None
            # The planner's own text gives flight-frame coordinates: not for the pilot.
            why = exc.reason.value.replace("_", " ")
            return Replan(None, f"no route any more to {{point}} ({why}); holding", goal)
        old = polyline_length(remaining)
        if blocked or route.length_m < (1 - cfg.replan_min_gain) * old:
            why = "the route was blocked" if blocked else "a shorter route opened"
            return Replan(route, f"{why}: new route {route.length_m:.2f} m (was {old:.2f} m to go)")
        self._planned_at = time_s
        return None

    def after_world_move(self, R: FloatArray, t: FloatArray, position: FloatArray) -> Replan:
        """The world moved under the goto (loop closure: ``R`` (3, 3), ``t`` (3,) map old
        flight-frame points to new ones) and the drone to ``position``: the route planned
        anew to the moved goal (which becomes the goal), or none (the drone holds); a route
        planned elsewhere (a course's autopilot, whose gates were laid in the old world) is not
        followed on."""
        _, goal = self._following()
        goal = R @ goal + t
        if self.replan is not None:
            return Replan(
                None, "the map was corrected (loop closure): the course's route is left; holding"
            )
        try:
            route = self.plan(position, goal, self.speed)
        except PlanningError as exc:
            why = exc.reason.value.replace("_", " ")
            return Replan(
                None,
                f"the map was corrected (loop closure) and no route is left to {{point}} "
                f"({why}); holding",
                goal,
            )
        self.goal = goal
        return Replan(
            route,
            f"the map was corrected (loop closure): new route {route.length_m:.2f} m to {{point}}",
            goal,
        )
