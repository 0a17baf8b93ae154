"""Polyline simplification: the few vertices a client needs to draw a densely sampled route.

Points are (N, 3) in any frame, metres.
"""

from __future__ import annotations

import numpy as np

from server.geometry.arrays import FloatArray, IndexArray


def distances_to_segment(points: FloatArray, a: FloatArray, b: FloatArray) -> FloatArray:
    """(N,) distance (m) from each of ``points`` (N, 3) to the segment a-b ((3,) each)."""
    ab = b - a
    length2 = float(ab @ ab)
    t = np.zeros(len(points)) if length2 == 0 else np.clip((points - a) @ ab / length2, 0, 1)
    distances: FloatArray = np.linalg.norm(points - (a + t[:, None] * ab), axis=1)
    return distances


def simplify(points: FloatArray, tolerance_m: float) -> IndexArray:
    """Indices (ascending, first and last included) of the vertices Douglas-Peucker keeps:
    every point lies within ``tolerance_m`` of the segment between the kept vertices around
    it, so straight segments drawn between the kept vertices stay that close to the polyline."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = len(p)
    if n <= 2:
        return np.arange(n)
    keep = np.zeros(n, dtype=bool)
    keep[[0, -1]] = True
    spans = [(0, n - 1)]
    while spans:  # explicit stack: a long wavy route must not hit the recursion limit
        a, b = spans.pop()
        if b - a < 2:
            continue
        d = distances_to_segment(p[a + 1 : b], p[a], p[b])
        k = int(np.argmax(d))
        if d[k] > tolerance_m:
            m = a + 1 + k
            keep[m] = True
            spans += [(a, m), (m, b)]
    return np.flatnonzero(keep)
