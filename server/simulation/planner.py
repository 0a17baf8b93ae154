"""Routes through the flight map: graph search on a lattice, shortcut, smoothed corners, timed.

1. **Lattice.** Nodes every ``cell_m`` (a whole number of map voxels) at cell centres of the
   map; a node is free when its clearance (the ESDF) is at least ``radius + margin``. Moves go to
   the 26 neighbours and cost their length times ``1 + clearance_weight * penalty``, where the
   penalty grows from 0 at ``preferred_clearance_m`` beyond the required clearance to 1 at it,
   so routes keep away from walls when they can. A move between nodes with clearances c_a, c_b
   and length L is allowed only when (c_a + c_b - L) / 2 >= radius + margin: the distance field
   is 1-Lipschitz, so the whole move keeps the clearance without sampling it.
2. **Search.** Dijkstra (scipy's, in C, which beats a Python A* by 10x here) from the nodes
   near the start (each joined to it by a free segment) to the nodes near the goal, first within
   a detour bound, then without. Connected components, computed with the graph once per map
   version, tell an unreachable goal at once. When the coarse lattice finds no route, the
   lattice of the map's own cells gets a try (narrow passages). A straight route is tried first.
3. **Shortcut.** From each kept vertex, jump to the farthest later vertex whose segment keeps
   the clearance the searched path had there (up to ``radius + margin + preferred_clearance_m``).
4. **Smooth.** Each corner becomes a quadratic Bezier blend between its two segments, checked
   against the map and shrunk (down to a stop at the corner) until it keeps the clearance.
5. **Time.** Speed limits from curvature (lateral acceleration), climb rate and max speed, then
   a forward-backward pass for the tangential acceleration; start and end at rest.

All positions are in the flight frame (metres, z up).
"""

from __future__ import annotations

import logging
import math
import weakref
from collections.abc import Sequence
from dataclasses import dataclass, field
from enum import Enum
from itertools import product

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import coo_matrix, csr_matrix
from scipy.sparse.csgraph import connected_components, dijkstra

from server.errors import ConfigError, DroneSimError
from server.geometry.arrays import BoolArray, FloatArray, IndexArray, RealArray
from server.simulation.flight_map import FlightMap

log = logging.getLogger(__name__)


class Reason(str, Enum):
    """Why no route was found; compares equal to its string value."""

    GOAL_BLOCKED = "goal_blocked"
    START_BLOCKED = "start_blocked"
    UNREACHABLE = "unreachable"
    OUTSIDE_MAP = "outside_map"
    NOT_FINITE = "not_finite"


class PlanningError(DroneSimError):
    """No route. ``reason``: a ``Reason``; ``nearest``: (3,) the free point nearest to the goal
    that a route from the start reaches (for ``start_blocked``: the free point nearest to the
    start), or None when there is none."""

    def __init__(self, reason: Reason, message: str, nearest: np.ndarray | None = None):
        super().__init__(message)
        self.reason = Reason(reason)
        self.nearest = None if nearest is None else np.asarray(nearest, dtype=np.float64)


@dataclass
class Route:
    """A timed route. ``points`` (N, 3): the shortcut polyline (start, corners, goal); ``path``
    (M, 3): the smoothed curve the drone follows, sampled densely, with ``times`` (M,) s and
    ``speeds`` (M,) m/s at each sample. Every path sample and ``points`` segment was checked
    against the map at the planning clearance."""

    points: FloatArray
    path: FloatArray
    times: FloatArray
    speeds: FloatArray
    length_m: float
    duration_s: float
    _tangents: FloatArray = field(repr=False)
    _curvatures: FloatArray = field(repr=False)  # curvature vectors kappa * normal, 1/m

    def sample(self, t_s: float | RealArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """(position, velocity, acceleration) at time ``t_s`` (clamped to the route): (3,) each
        for a scalar time, (K, 3) each for K times. Speed along the path changes with constant
        acceleration between samples."""
        t = np.clip(np.asarray(t_s, dtype=np.float64), 0.0, self.duration_s)
        scalar = t.ndim == 0
        t = t.reshape(-1)
        if len(self.path) == 1:
            zeros = np.zeros((len(t), 3))
            position: FloatArray = np.repeat(self.path, len(t), axis=0)
            return _first_if(scalar, position, zeros, zeros.copy())
        i = np.clip(np.searchsorted(self.times, t, side="right") - 1, 0, len(self.path) - 2)
        ds = np.linalg.norm(self.path[i + 1] - self.path[i], axis=1)
        v0, v1 = self.speeds[i], self.speeds[i + 1]
        accel = (v1**2 - v0**2) / (2 * np.maximum(ds, 1e-12))
        tau = t - self.times[i]
        speed = np.clip(v0 + accel * tau, 0.0, np.maximum(v0, v1))
        frac = np.clip((v0 * tau + 0.5 * accel * tau**2) / np.maximum(ds, 1e-12), 0.0, 1.0)
        f = frac[:, None]
        position = self.path[i] + f * (self.path[i + 1] - self.path[i])
        tangent = (1 - f) * self._tangents[i] + f * self._tangents[i + 1]
        tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-12)
        curvature = (1 - f) * self._curvatures[i] + f * self._curvatures[i + 1]
        velocity = speed[:, None] * tangent
        acceleration = accel[:, None] * tangent + (speed**2)[:, None] * curvature
        return _first_if(scalar, position, velocity, acceleration)


def _first_if(
    scalar: bool, position: FloatArray, velocity: FloatArray, acceleration: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Route.sample's result: the (K, 3) arrays, or their first rows for a scalar time."""
    if scalar:
        return position[0], velocity[0], acceleration[0]
    return position, velocity, acceleration


@dataclass
class _Lattice:
    """The planning graph of one map version and clearance. Node n (flat index into ``shape``)
    sits at ``base + unravel(n) * cell_m``; ``graph`` joins free nodes by allowed moves."""

    base: FloatArray
    cell_m: float
    required_m: float  # clearance of a free node
    shape: tuple[int, ...]  # 3 axes
    free: BoolArray  # (shape)
    penalty: FloatArray  # flat, per node
    graph: csr_matrix  # move costs (symmetric), metres
    labels: NDArray[np.int32]  # flat connected-component label per node

    def positions(self, flat: IndexArray) -> FloatArray:
        return self.base + np.stack(np.unravel_index(flat, self.shape), axis=-1) * self.cell_m


# (map version, required clearance, cell, clearance weight, preferred clearance)
_LatticeKey = tuple[int, float, float, float, float]
_LATTICES: weakref.WeakKeyDictionary[FlightMap, dict[_LatticeKey, _Lattice]] = (
    weakref.WeakKeyDictionary()
)


def _lattice(
    flight_map: FlightMap, required_m: float, cell_m: float, weight: float, preferred_m: float
) -> _Lattice:
    """The lattice for these settings, built once per map version."""
    key: _LatticeKey = (flight_map.version, required_m, cell_m, weight, preferred_m)
    cached = _LATTICES.setdefault(flight_map, {})
    if key in cached:
        return cached[key]
    v = flight_map.voxel_m
    step = max(1, round(cell_m / v))
    off = step // 2
    clearance = flight_map.esdf[off::step, off::step, off::step].astype(np.float64)
    free = clearance >= required_m
    penalty = weight * np.clip(1.0 - (clearance - required_m) / preferred_m, 0.0, 1.0) ** 2
    cell, shape = step * v, clearance.shape
    # Moves to the 13 "forward" neighbours of every free node (the graph is undirected).
    ijk = np.argwhere(free)
    flat_clear, flat_pen = clearance.ravel(), penalty.ravel()
    rows: list[IndexArray] = []
    cols: list[IndexArray] = []
    costs: list[FloatArray] = []
    for d in product((-1, 0, 1), repeat=3):
        if d <= (0, 0, 0):
            continue
        length = cell * math.sqrt(d[0] ** 2 + d[1] ** 2 + d[2] ** 2)
        to = ijk + d
        inside = np.all((to >= 0) & (to < shape), axis=1)
        a = np.ravel_multi_index(tuple(ijk[inside].T), shape)
        b = np.ravel_multi_index(tuple(to[inside].T), shape)
        ok = free.ravel()[b] & (flat_clear[a] + flat_clear[b] >= 2 * required_m + length)
        a, b = a[ok], b[ok]
        rows.append(a)
        cols.append(b)
        costs.append(length * (1.0 + 0.5 * (flat_pen[a] + flat_pen[b])))
    n = int(np.prod(shape))
    row, col, cost = np.concatenate(rows), np.concatenate(cols), np.concatenate(costs)
    # Both directions stored: scipy would otherwise transpose the graph on every search.
    graph = coo_matrix(
        (
            np.concatenate([cost, cost]),
            (np.concatenate([row, col]), np.concatenate([col, row])),
        ),
        shape=(n, n),
    ).tocsr()
    labels = connected_components(graph, directed=True, connection="weak")[1]
    labels[~free.ravel()] = -1
    lattice = _Lattice(
        flight_map.origin + (off + 0.5) * v, cell, required_m, shape, free, flat_pen, graph, labels
    )
    if any(k[0] != flight_map.version for k in cached):
        cached.clear()  # the map changed: older lattices are stale
    cached[key] = lattice
    return lattice


def _nodes_near(
    flight_map: FlightMap, lattice: _Lattice, point: FloatArray, hard_m: float, reach: int = 2
) -> tuple[IndexArray, FloatArray]:
    """Free nodes within ``reach`` lattice steps of ``point`` joined to it by a segment that
    keeps ``hard_m``: (flat indices, segment lengths)."""
    u = np.floor((point - lattice.base) / lattice.cell_m).astype(np.int64)
    grid = np.stack(np.meshgrid(*[np.arange(-reach + 1, reach + 1)] * 3, indexing="ij"), -1)
    ijk = u + grid.reshape(-1, 3)
    ijk = ijk[np.all((ijk >= 0) & (ijk < lattice.shape), axis=1)]
    ijk = ijk[lattice.free[tuple(ijk.T)]]
    if len(ijk) == 0:
        return np.empty(0, np.int64), np.empty(0)
    positions = lattice.base + ijk * lattice.cell_m
    ok = flight_map.segments_free(np.repeat(point[None], len(ijk), 0), positions, hard_m)
    flat = np.ravel_multi_index(tuple(ijk[ok].T), lattice.shape)
    return flat, np.linalg.norm(positions[ok] - point, axis=1)


def _search(
    lattice: _Lattice,
    sources: IndexArray,
    targets: IndexArray,
    target_costs: FloatArray,
    limit_m: float,
) -> list[int] | None:
    """Dijkstra (scipy, in C) from every source at once, explored up to a cost of ``limit_m``;
    returns the node path to the target with the least cost plus connection cost, or None."""
    cost, pred, _ = dijkstra(
        lattice.graph,
        directed=True,
        indices=sources,
        min_only=True,
        return_predecessors=True,
        limit=limit_m,
    )
    total = cost[targets] + target_costs
    best = int(np.argmin(total))
    if not np.isfinite(total[best]):
        return None
    path: list[int] = []
    n = int(targets[best])
    while n >= 0:
        path.append(n)
        n = int(pred[n])
    return path[::-1]


# --- shortcut, smoothing, timing ---------------------------------------------------------------
def _shortcut(
    flight_map: FlightMap,
    raw: FloatArray,
    clear_raw: FloatArray,
    required_m: float,
    wanted_m: float,
    slack_m: float,
) -> FloatArray:
    """Greedy line-of-sight shortcut of the raw path (K, 3) whose vertices have clearances
    clear_raw (K,): a jump i -> j must keep the clearance the raw path had between them (less
    ``slack_m`` for its edges, at most ``wanted_m``) and at least ``required_m`` (or what its
    ends have, when an end has less)."""
    keep, i, last = [0], 0, len(raw) - 1
    step = np.diff(raw, axis=0)
    turns = np.flatnonzero(np.any(np.abs(step[1:] - step[:-1]) > 1e-9, axis=1)) + 1
    ends = np.union1d(turns, [1, last])  # lattice runs are straight: jump only to their ends
    while i < last:
        js = ends[ends > i]
        seg = flight_map.segment_clearances(np.repeat(raw[i][None], len(js), 0), raw[js])
        had = np.minimum.accumulate(clear_raw[i + 1 :])[js - i - 1]
        need = np.maximum(
            np.minimum(required_m, np.minimum(clear_raw[i], clear_raw[js])),
            np.minimum(wanted_m, np.minimum(had, clear_raw[i]) - slack_m),
        )
        ok = seg >= need - 1e-9
        if not ok.any():  # the raw run itself: kept clear by the search's move rule
            ok[0], js[0] = True, i + 1
        i = int(js[np.flatnonzero(ok)[-1]])
        keep.append(i)
    return raw[keep]


def _bezier(
    p: FloatArray, u1: FloatArray, u2: FloatArray, d: float, step_m: float
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Samples of the quadratic Bezier corner blend at p with arms d along -u1 and u2:
    positions, unit tangents, curvature vectors."""
    a, b = p - d * u1, p + d * u2
    u = np.linspace(0.0, 1.0, max(3, math.ceil(2 * d / step_m) + 1))[:, None]
    pos = (1 - u) ** 2 * a + 2 * u * (1 - u) * p + u**2 * b
    d1 = 2 * d * ((1 - u) * u1 + u * u2)
    d2 = 2 * d * (u2 - u1)
    speed2 = np.sum(d1**2, axis=1, keepdims=True)
    tangent = d1 / np.sqrt(speed2)
    kvec = (d2 - np.sum(d2 * tangent, axis=1, keepdims=True) * tangent) / speed2
    return pos, tangent, kvec


def _smooth(
    flight_map: FlightMap, pts: FloatArray, floor_m: float, step_m: float, max_arm_m: float = 1.0
) -> tuple[FloatArray, FloatArray, FloatArray, BoolArray]:
    """Dense samples of the polyline with each corner blended: (positions, tangents, curvature
    vectors, stop flags). A blend must keep min(floor_m, its segments' clearance); it is halved
    until it does, and after 6 halvings the drone stops at the corner instead."""
    seg_clear = flight_map.segment_clearances(pts[:-1], pts[1:])
    lengths = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    dirs = np.diff(pts, axis=0) / lengths[:, None]
    # Pieces of (positions, tangents, curvature vectors, stop flags).
    out: list[tuple[FloatArray, FloatArray, FloatArray, BoolArray]] = [
        (pts[:1], dirs[:1], np.zeros((1, 3)), np.array([False]))
    ]
    current = pts[0]

    def line_to(q: FloatArray, direction: FloatArray) -> None:
        n = math.ceil(np.linalg.norm(q - current) / step_m)
        if n:
            t = np.linspace(0.0, 1.0, n + 1)[1:, None]
            out.append(
                (
                    current + t * (q - current),
                    np.repeat(direction[None], n, 0),
                    np.zeros((n, 3)),
                    np.zeros(n, bool),
                )
            )

    for k in range(1, len(pts) - 1):
        u1, u2 = dirs[k - 1], dirs[k]
        avail_in = lengths[k - 1] * (1.0 if k == 1 else 0.5)
        avail_out = lengths[k] * (1.0 if k == len(pts) - 2 else 0.5)
        d = min(avail_in, avail_out, max_arm_m)
        keep = min(floor_m, seg_clear[k - 1], seg_clear[k]) - 1e-9
        blend: tuple[FloatArray, FloatArray, FloatArray] | None = None
        for _ in range(6 if np.dot(u1, u2) > -0.999 else 0):  # a U-turn has no blend
            blend = _bezier(pts[k], u1, u2, d, step_m)
            if flight_map.distance(blend[0]).min() >= keep:
                break
            d *= 0.5
        else:
            blend = None
        if blend is None:  # stop at the corner: arrive along u1, leave along u2
            line_to(pts[k], u1)
            out[-1][3][-1] = True
            out.append((pts[k][None], u2[None], np.zeros((1, 3)), np.array([True])))
        else:
            line_to(blend[0][0], u1)
            n = len(blend[0]) - 1
            out.append((blend[0][1:], blend[1][1:], blend[2][1:], np.zeros(n, bool)))
        current = out[-1][0][-1]
    line_to(pts[-1], dirs[-1])
    positions, tangents, kvecs, stops = zip(*out, strict=True)
    return (
        np.concatenate(positions),
        np.concatenate(tangents),
        np.concatenate(kvecs),
        np.concatenate(stops),
    )


def _time(
    path: FloatArray,
    tangents: FloatArray,
    kvecs: FloatArray,
    stops: BoolArray,
    max_speed: float,
    max_accel: float,
    max_climb: float | None,
) -> tuple[FloatArray, FloatArray]:
    """Speeds at the samples: curvature, climb and speed limits, then forward-backward passes
    with half the acceleration budget (each of tangential and lateral gets a_max / sqrt 2)."""
    ds = np.linalg.norm(np.diff(path, axis=0), axis=1)
    a = max_accel / math.sqrt(2.0)
    kappa = np.linalg.norm(kvecs, axis=1)
    limit = np.minimum(max_speed, np.sqrt(a / np.maximum(kappa, 1e-12)))
    if max_climb is not None:
        limit = np.minimum(limit, max_climb / np.maximum(np.abs(tangents[:, 2]), 1e-12))
    limit[stops] = 0.0
    limit[[0, -1]] = 0.0
    v = limit.tolist()
    steps = (2 * a * ds).tolist()
    for i in range(1, len(v)):
        v[i] = min(v[i], math.sqrt(v[i - 1] ** 2 + steps[i - 1]))
    for i in range(len(v) - 2, -1, -1):
        v[i] = min(v[i], math.sqrt(v[i + 1] ** 2 + steps[i]))
    speeds = np.array(v)
    # Between two standstills (consecutive stops) the segment takes an accelerate-decelerate
    # time instead of an unbounded one.
    mean2 = speeds[:-1] + speeds[1:]
    dt = np.where(mean2 > 1e-9, 2 * ds / np.maximum(mean2, 1e-9), 2 * np.sqrt(ds / a))
    return speeds, np.concatenate([[0.0], np.cumsum(dt)])


# --- the public calls ------------------------------------------------------------------------
def _fmt(p: FloatArray) -> str:
    return "(" + ", ".join(f"{x:.2f}" for x in np.asarray(p).reshape(-1)) + ")"


def _nearest_reachable(
    lattice: _Lattice, sources: IndexArray, goal: FloatArray
) -> FloatArray | None:
    """The lattice node nearest to ``goal`` in the components of ``sources``, or None."""
    if len(sources) == 0:
        return None
    nodes = lattice.positions(np.flatnonzero(np.isin(lattice.labels, lattice.labels[sources])))
    nearest: FloatArray = nodes[np.argmin(np.linalg.norm(nodes - goal, axis=1))]
    return nearest


def _endpoint_nodes(
    flight_map: FlightMap, lattice: _Lattice, point: FloatArray, radius_m: float
) -> tuple[IndexArray, FloatArray]:
    for reach in (2, 4):
        flat, lengths = _nodes_near(flight_map, lattice, point, radius_m, reach)
        if len(flat):
            return flat, lengths
    return flat, lengths


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
            f"start {_fmt(start)} is outside the map {_fmt(bounds.lo)}..{_fmt(bounds.hi)}",
            flight_map.nearest_free(start, required),
        )
    c_start = float(flight_map.distance(start))
    if c_start < radius_m:
        raise PlanningError(
            Reason.START_BLOCKED,
            f"start {_fmt(start)} has {c_start:.2f} m clearance, less than the "
            f"radius {radius_m:.2f} m",
            flight_map.nearest_free(start, required),
        )
    lattice = _lattice(flight_map, required, cell_m, clearance_weight, preferred_clearance_m)
    sources, _ = _endpoint_nodes(flight_map, lattice, start, radius_m)
    if not bounds.contains(goal)[0]:
        raise PlanningError(
            Reason.OUTSIDE_MAP,
            f"goal {_fmt(goal)} is outside the map {_fmt(bounds.lo)}..{_fmt(bounds.hi)}",
            _nearest_reachable(lattice, sources, goal),
        )
    c_goal = float(flight_map.distance(goal))
    if c_goal < radius_m:
        raise PlanningError(
            Reason.GOAL_BLOCKED,
            f"goal {_fmt(goal)} is in or too close to an obstacle ({c_goal:.2f} m "
            f"clearance, radius {radius_m:.2f} m)",
            _nearest_reachable(lattice, sources, goal),
        )

    # A straight route when it is as clear as its ends allow; else search the lattice.
    wanted = required + preferred_clearance_m
    direct = flight_map.segment_clearance(start, goal)
    if direct >= min(wanted, c_start, c_goal) - 1e-9:
        raw = np.stack([start, goal])
    else:
        raw = _search_lattices(
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
    corners = _shortcut(flight_map, raw, clear_raw, required, wanted, 0.9 * lattice.cell_m)
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
    path, tangents, kvecs, stops = _smooth(flight_map, corners, clearance_m, step)
    if len(path) == 2:  # shorter than one step: a midpoint lets the speed rise and fall again
        path = np.stack([path[0], path.mean(axis=0), path[1]])
        tangents, kvecs = tangents[[0, 0, 1]], np.zeros((3, 3))
        stops = np.array([stops[0], False, stops[1]])
    speeds, times = _time(
        path, tangents, kvecs, stops, max_speed_m_s, max_accel_m_s2, max_climb_rate_m_s
    )
    length = float(np.sum(np.linalg.norm(np.diff(path, axis=0), axis=1)))
    return Route(corners, path, times, speeds, length, float(times[-1]), tangents, kvecs)


def _search_lattices(
    flight_map: FlightMap,
    start: FloatArray,
    goal: FloatArray,
    radius_m: float,
    lattice: _Lattice,
    sources: IndexArray,
    settings: tuple[float, float, float],
    detour: float,
) -> FloatArray:
    """The raw path through the coarse lattice, or, where that finds none, through the lattice
    of the map's own cells (built on demand: narrow passages the coarse one cannot see)."""
    try:
        return _search_route(flight_map, lattice, start, goal, radius_m, sources, detour)
    except PlanningError as exc:
        if exc.reason == Reason.GOAL_BLOCKED or lattice.cell_m <= flight_map.voxel_m * 1.01:
            raise
        log.debug("coarse lattice: %s; trying the map's own cells", exc)
    fine = _lattice(flight_map, settings[0], flight_map.voxel_m, settings[1], settings[2])
    sources, _ = _endpoint_nodes(flight_map, fine, start, radius_m)
    return _search_route(flight_map, fine, start, goal, radius_m, sources, detour)


def _search_route(
    flight_map: FlightMap,
    lattice: _Lattice,
    start: FloatArray,
    goal: FloatArray,
    radius_m: float,
    sources: IndexArray,
    detour: float,
) -> FloatArray:
    """The raw path (K, 3) from start through the lattice to goal, or PlanningError."""
    if len(sources) == 0:
        raise PlanningError(
            Reason.START_BLOCKED,
            f"no free lattice node next to the start {_fmt(start)}: it is boxed in",
            flight_map.nearest_free(start, lattice.required_m),
        )
    targets, target_lengths = _endpoint_nodes(flight_map, lattice, goal, radius_m)
    if not np.intersect1d(lattice.labels[sources], lattice.labels[targets]).size:
        raise PlanningError(
            Reason.UNREACHABLE,
            f"goal {_fmt(goal)} is not connected to the start {_fmt(start)} through free space",
            _nearest_reachable(lattice, sources, goal),
        )
    target_costs = target_lengths * (1 + lattice.penalty[targets])
    # Most routes stay within a small detour: explore that far first, then everything.
    limit = detour * float(np.linalg.norm(goal - start)) + 1.0
    nodes = _search(lattice, sources, targets, target_costs, limit)
    if nodes is None:
        nodes = _search(lattice, sources, targets, target_costs, np.inf)
    return np.concatenate([start[None], lattice.positions(np.array(nodes)), goal[None]])


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
