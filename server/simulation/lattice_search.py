"""Graph search for the planner: a lattice over the flight map's free space, searched by Dijkstra.

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
   lattice of the map's own cells gets a try (narrow passages).

The planner (planner.py) calls ``lattice_for``, ``endpoint_nodes``, ``nearest_reachable`` and
``search_lattices``. All positions are in the flight frame (metres, z up).
"""

from __future__ import annotations

import logging
import math
import weakref
from dataclasses import dataclass
from itertools import product

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import coo_matrix, csr_matrix
from scipy.sparse.csgraph import connected_components, dijkstra

from server.geometry.arrays import BoolArray, FloatArray, IndexArray
from server.simulation.flight_map import FlightMap
from server.simulation.route import PlanningError, Reason, fmt_point

log = logging.getLogger(__name__)


@dataclass
class Lattice:
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
_LATTICES: weakref.WeakKeyDictionary[FlightMap, dict[_LatticeKey, Lattice]] = (
    weakref.WeakKeyDictionary()
)


def lattice_for(
    flight_map: FlightMap, required_m: float, cell_m: float, weight: float, preferred_m: float
) -> Lattice:
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
    lattice = Lattice(
        flight_map.origin + (off + 0.5) * v, cell, required_m, shape, free, flat_pen, graph, labels
    )
    if any(k[0] != flight_map.version for k in cached):
        cached.clear()  # the map changed: older lattices are stale
    cached[key] = lattice
    return lattice


def _nodes_near(
    flight_map: FlightMap, lattice: Lattice, point: FloatArray, hard_m: float, reach: int = 2
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
    lattice: Lattice,
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


def nearest_reachable(lattice: Lattice, sources: IndexArray, goal: FloatArray) -> FloatArray | None:
    """The lattice node nearest to ``goal`` in the components of ``sources``, or None."""
    if len(sources) == 0:
        return None
    nodes = lattice.positions(np.flatnonzero(np.isin(lattice.labels, lattice.labels[sources])))
    nearest: FloatArray = nodes[np.argmin(np.linalg.norm(nodes - goal, axis=1))]
    return nearest


def endpoint_nodes(
    flight_map: FlightMap, lattice: Lattice, point: FloatArray, radius_m: float
) -> tuple[IndexArray, FloatArray]:
    """The free nodes a route may leave ``point`` by (or reach it from), as ``_nodes_near``:
    those within 2 lattice steps, else within 4."""
    for reach in (2, 4):
        flat, lengths = _nodes_near(flight_map, lattice, point, radius_m, reach)
        if len(flat):
            return flat, lengths
    return flat, lengths


def search_lattices(
    flight_map: FlightMap,
    start: FloatArray,
    goal: FloatArray,
    radius_m: float,
    lattice: Lattice,
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
    fine = lattice_for(flight_map, settings[0], flight_map.voxel_m, settings[1], settings[2])
    sources, _ = endpoint_nodes(flight_map, fine, start, radius_m)
    return _search_route(flight_map, fine, start, goal, radius_m, sources, detour)


def _search_route(
    flight_map: FlightMap,
    lattice: Lattice,
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
            f"no free lattice node next to the start {fmt_point(start)}: it is boxed in",
            flight_map.nearest_free(start, lattice.required_m),
        )
    targets, target_lengths = endpoint_nodes(flight_map, lattice, goal, radius_m)
    if not np.intersect1d(lattice.labels[sources], lattice.labels[targets]).size:
        raise PlanningError(
            Reason.UNREACHABLE,
            f"goal {fmt_point(goal)} is not connected to the start {fmt_point(start)} "
            "through free space",
            nearest_reachable(lattice, sources, goal),
        )
    target_costs = target_lengths * (1 + lattice.penalty[targets])
    # Most routes stay within a small detour: explore that far first, then everything.
    limit = detour * float(np.linalg.norm(goal - start)) + 1.0
    nodes = _search(lattice, sources, targets, target_costs, limit)
    if nodes is None:
        nodes = _search(lattice, sources, targets, target_costs, np.inf)
    return np.concatenate([start[None], lattice.positions(np.array(nodes)), goal[None]])
