"""Parts of the flight map's space (flight frame, metres, z up): an axis-aligned ``Box`` (what a
map change touched) and a ``Region``, occupancy for a sub-box as the map takes it in an update
(server/simulation/flight_map.py)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from server.geometry.arrays import BoolArray, FloatArray
from server.simulation.esdf import slices


@dataclass(frozen=True)
class Box:
    """Axis-aligned box in the flight frame: ``lo`` and ``hi`` (3,) corners, metres."""

    lo: FloatArray
    hi: FloatArray

    def contains(self, points: ArrayLike, margin_m: float = 0.0) -> BoolArray:
        """(N,) bool: which points (N, 3) lie in the box grown by ``margin_m``."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        inside: BoolArray = np.all((p >= self.lo - margin_m) & (p <= self.hi + margin_m), axis=1)
        return inside


@dataclass(frozen=True)
class Region:
    """Occupancy for a sub-box of the flight map, as ``FlightMap.update_region`` takes it:
    ``origin`` (3,) corner of cell (0, 0, 0), metres, on the map's lattice; ``occupied``,
    ``observed`` and ``written`` (the cells it sets), (X, Y, Z) bool each."""

    origin: FloatArray
    occupied: BoolArray
    observed: BoolArray
    written: BoolArray

    @classmethod
    def whole(cls, origin: ArrayLike, occupied: BoolArray, observed: BoolArray) -> Region:
        """A region that sets every cell of its box."""
        return cls(
            np.asarray(origin, dtype=np.float64),
            occupied,
            observed,
            np.ones(np.shape(occupied), dtype=bool),
        )

    def merged(self, newer: Region, voxel_m: float) -> Region:
        """One region setting what both set (``newer`` wins where both do), in the smallest
        box holding both; both must sit on one lattice of ``voxel_m`` cells."""
        step = np.round((newer.origin - self.origin) / voxel_m).astype(np.int64)
        lo = np.minimum(0, step)
        hi = np.maximum(self.occupied.shape, step + newer.occupied.shape)
        out = [np.zeros(hi - lo, dtype=bool) for _ in range(3)]
        for part, at in ((self, -lo), (newer, step - lo)):
            box = slices(at, at + part.occupied.shape)
            w = part.written
            for dst, src in zip(out, (part.occupied, part.observed, part.written), strict=True):
                dst[box][w] = src[w]
        return Region(self.origin + lo * voxel_m, *out)
