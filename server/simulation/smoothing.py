"""Shaping the planner's raw path into a route: shortcut, smoothed corners, timed.

3. **Shortcut** (``shortcut``). From each kept vertex, jump to the farthest later vertex whose
   segment keeps the clearance the searched path had there (up to ``radius + margin +
   preferred_clearance_m``).
4. **Smooth** (``smooth``). Each corner becomes a quadratic Bezier blend between its two
   segments, checked against the map and shrunk (down to a stop at the corner) until it keeps
   the clearance.
5. **Time** (``speeds_and_times``). Speed limits from curvature (lateral acceleration), climb
   rate and max speed, then a forward-backward pass for the tangential acceleration; start and
   end at rest.

Steps 1 and 2 (the lattice and its search) are in lattice_search.py; planner.py runs them all.
All positions are in the flight frame (metres, z up).
"""

from __future__ import annotations

import math

import numpy as np

from server.geometry.arrays import BoolArray, FloatArray
from server.simulation.flight_map import FlightMap


def shortcut(
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


def smooth(
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


def speeds_and_times(
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
