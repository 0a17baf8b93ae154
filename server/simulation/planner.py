"""Routes through the flight map: graph search on a lattice, shortcut, smoothed corners, timed.

``plan_path`` runs the stages top to bottom; each lives in a module of its own:

1. **Lattice** and 2. **search** (lattice_search.py): nodes every ``cell_m`` with the
   clearance the route needs, joined by moves that keep it; Dijkstra from the start's nodes to
   the goal's (the map's own cells get a try when the coarse lattice finds no route). A
   straight route is tried first.
3. **Shortcut**, 4. **smooth** and 5. **time** (smoothing.py): the farthest jumps that keep
   the searched path's clearance, corners blended where the blend stays clear, then speeds from
   curvature, climb rate and acceleration, starting and ending at rest.

The answer is a ``Route``, or a ``PlanningError`` with its ``Reason`` (route.py). All positions
are in the flight frame (metres, z up).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from server.errors import ConfigError
from server.geometry.arrays import FloatArray
from server.simulation.flight_map import FlightMap
from server.simulation.lattice_search import (
    endpoint_nodes,
    lattice_for,
    nearest_reachable,
    search_lattices,
)
from server.simulation.route import PlanningError, Reason, Route, fmt_point
from server.simulation.smoothing import shortcut, smooth, speeds_and_times


def plan_path(
    flight_map: FlightMap,
    start: Sequence[float] | FloatArray,
    goal: Sequence[float] | FloatArray,
    radius_m: float,
    *,
    margin_m: float | None = None,
    cell_m: float = 0.1,
    clearance_weight: float = 1.0,
    preferred_clearance_m: float = 0.3,
    max_speed_m_s: float = 1.0,
    max_accel_m_s2: float = 2.0,
    max_climb_rate_m_s: float | None = None,
    search_detour: float = 3.0,
) -> Route:
    """A timed route for a sphere of ``radius_m`` from ``start`` to ``goal`` ((3,), flight
    frame, metres), starting and ending at rest.

    margin_m: extra clearance the route keeps beyond radius_m (None: half a voxel, which
    covers the distance field's error near obstacle edges); the start and goal need only
    radius_m. cell_m: lattice step of the search (rounded to whole voxels).
    clearance_weight, preferred_clearance_m: moves with less than radius + margin +
    preferred_clearance_m clearance cost up to (1 + clearance_weight) times their length.
    max_speed_m_s, max_accel_m_s2, max_climb_rate_m_s (None: no separate limit): the timing.
    search_detour: the search first explores routes costing up to this many times the
    straight distance (plus 1 m), then, when none reaches the goal, all of them.
    Raises PlanningError (see ``Reason``) when there is no route.
    """
    start = np.asarray(start, dtype=np.float64).reshape(-1)
    goal = np.asarray(goal, dtype=np.float64).reshape(-1)
    if start.shape != (3,) or goal.shape != (3,):
        raise ConfigError(f"start and goal must be 3-vectors, got {start.shape} and {goal.shape}")
    if not (np.all(np.isfinite(start)) and np.all(np.isfinite(goal)) and math.isfinite(radius_m)):
        raise PlanningError(
            Reason.NOT_FINITE, f"start {start}, goal {goal} and radius {radius_m} must be finite"
        )
    if radius_m < 0 or cell_m <= 0 or max_speed_m_s <= 0 or max_accel_m_s2 <= 0:
        raise ConfigError("radius must be >= 0 and cell, speed and acceleration limits > 0")
    margin = 0.5 * flight_map.voxel_m if margin_m is None else margin_m
    required = radius_m + margin
    bounds = flight_map.bounds
    if not bounds.contains(start)[0]:
        raise PlanningError(
            Reason.OUTSIDE_MAP,
            f"start {fmt_point(start)} is outside the map "
            f"{fmt_point(bounds.lo)}..{fmt_point(bounds.hi)}",
            flight_map.nearest_free(start, required),
        )
    c_start = float(flight_map.distance(start))
    if c_start < radius_m:
        raise PlanningError(
            Reason.START_BLOCKED,
            f"start {fmt_point(start)} has {c_start:.2f} m clearance, less than the "
            f"radius {radius_m:.2f} m",
            flight_map.nearest_free(start, required),
        )
    lattice = lattice_for(flight_map, required, cell_m, clearance_weight, preferred_clearance_m)
    sources, _ = endpoint_nodes(flight_map, lattice, start, radius_m)
    if not bounds.contains(goal)[0]:
        raise PlanningError(
            Reason.OUTSIDE_MAP,
            f"goal {fmt_point(goal)} is outside the map "
            f"{fmt_point(bounds.lo)}..{fmt_point(bounds.hi)}",
            nearest_reachable(lattice, sources, goal),
        )
    c_goal = float(flight_map.distance(goal))
    if c_goal < radius_m:
        raise PlanningError(
            Reason.GOAL_BLOCKED,
            f"goal {fmt_point(goal)} is in or too close to an obstacle ({c_goal:.2f} m "
            f"clearance, radius {radius_m:.2f} m)",
            nearest_reachable(lattice, sources, goal),
        )

    # A straight route when it is as clear as its ends allow; else search the lattice.
    wanted = required + preferred_clearance_m
    direct = flight_map.segment_clearance(start, goal)
    if direct >= min(wanted, c_start, c_goal) - 1e-9:
        raw = np.stack([start, goal])
    else:
        raw = search_lattices(
            flight_map,
            start,
            goal,
            radius_m,
            lattice,
            sources,
            (required, clearance_weight, preferred_clearance_m),
            search_detour,
        )
    raw = raw[np.concatenate([[True], np.linalg.norm(np.diff(raw, axis=0), axis=1) > 1e-9])]
    if len(raw) == 1:  # already there
        zero = np.zeros((1, 3))
        return Route(raw, raw.copy(), np.zeros(1), np.zeros(1), 0.0, 0.0, zero, zero.copy())
    clear_raw = np.asarray(flight_map.distance(raw))
    corners = shortcut(flight_map, raw, clear_raw, required, wanted, 0.9 * lattice.cell_m)
    return timed_route(
        flight_map, corners, required, max_speed_m_s, max_accel_m_s2, max_climb_rate_m_s
    )


def timed_route(
    flight_map: FlightMap,
    corners: FloatArray,
    clearance_m: float,
    max_speed_m_s: float,
    max_accel_m_s2: float,
    max_climb_rate_m_s: float | None = None,
) -> Route:
    """Steps 4 and 5 for a polyline of corners (K >= 2, (K, 3) flight frame, metres, no two in
    a row equal) already clear of the map: each corner blended where the blend keeps
    ``clearance_m`` (or what its segments have), then timed from rest to rest. ``plan_path``
    ends with it; a course's autopilot joins its legs and gates with it."""
    step = min(0.02, 0.5 * flight_map.voxel_m)
    path, tangents, kvecs, stops = smooth(flight_map, corners, clearance_m, step)
    if len(path) == 2:  # shorter than one step: a midpoint lets the speed rise and fall again
        path = np.stack([path[0], path.mean(axis=0), path[1]])
        tangents, kvecs = tangents[[0, 0, 1]], np.zeros((3, 3))
        stops = np.array([stops[0], False, stops[1]])
    speeds, times = speeds_and_times(
        path, tangents, kvecs, stops, max_speed_m_s, max_accel_m_s2, max_climb_rate_m_s
    )
    length = float(np.sum(np.linalg.norm(np.diff(path, axis=0), axis=1)))
    return Route(corners, path, times, speeds, length, float(times[-1]), tangents, kvecs)


def route_is_clear(
    flight_map: FlightMap, route: Route, radius_m: float, from_time_s: float = 0.0
) -> bool:
    """Whether the part of ``route`` from ``from_time_s`` on still keeps ``radius_m`` in
    ``flight_map`` (e.g. after a map update)."""
    i = max(int(np.searchsorted(route.times, from_time_s, side="right")) - 1, 0)
    rest = route.path[i:]
    if len(rest) == 1:
        return bool(flight_map.is_free(rest, radius_m)[0])
    return bool(np.all(flight_map.segments_free(rest[:-1], rest[1:], radius_m)))
