"""The drone's world model: an occupancy grid and its Euclidean signed distance field (ESDF).

Flight frame: metres, z up. Cell (i, j, k) spans ``origin + [i, i + 1) * voxel_m`` along x (and
likewise j along y, k along z). A cell is *blocked* when it is occupied, or unobserved and
``unknown_is_free`` is False; space outside the grid counts as unobserved.

The field is stored at cell centres: for a free cell, the distance between its centre and the
nearest blocked cell's centre minus half a voxel (so a face neighbour of a wall reads +v/2, the
distance to the wall's face); for a blocked cell, minus the same towards the nearest free cell.
It is clipped to +-``max_distance_m``. Queries interpolate it trilinearly, so a point on a wall's
face reads 0. Near edges and corners of obstacles the centre-to-centre distance, and its
interpolation, overstate the distance to the cells' boundary: by up to ~0.4 voxel around boxes
and ~0.6 voxel around isolated cells; callers that need a hard guarantee keep a margin (the
planner keeps half a voxel beyond the radius it is given).

The grid is stored with a one-cell ring around it holding the "outside" state, which makes the
field exactly that of the infinite lattice (the ring shields the interior from everything beyond
it), so incremental updates can be checked against a full rebuild exactly. ``FlightMap`` keeps
the grid and answers queries; esdf.py computes the field, whole or around what changed.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable
from typing import Literal, overload

import numpy as np
from numpy.typing import ArrayLike

from server.errors import ConfigError, DroneSimError
from server.geometry.arrays import BoolArray, Float32Array, FloatArray, Int64Array
from server.simulation.esdf import padded, reach_cells, signed_distance, slices, updated_field
from server.simulation.map_regions import Box

log = logging.getLogger(__name__)

_LATTICE_TOL = 1e-3  # origins closer than this (in voxels) to the lattice count as on it


class FlightMapError(DroneSimError):
    """A grid given to the flight map is malformed."""


class FlightMap:
    """Occupancy grid plus ESDF, replaced grid by grid as the session's map grows."""

    def __init__(
        self, voxel_m: float = 0.05, unknown_is_free: bool = False, max_distance_m: float = 1.0
    ) -> None:
        """voxel_m: cell edge (m). unknown_is_free: treat unobserved cells (and the outside of
        the grid) as free instead of blocked. max_distance_m: the field is clipped to +- this
        (m); it also bounds how far an incremental update recomputes around a change, so it is
        kept short: 1 m is 21 cells at 5 cm, and nothing here needs clearances beyond it."""
        if not (voxel_m > 0 and max_distance_m > 0):
            raise ConfigError(
                f"voxel_m and max_distance_m must be positive, got {voxel_m}, {max_distance_m}"
            )
        self.voxel_m = float(voxel_m)
        self.unknown_is_free = bool(unknown_is_free)
        self.max_distance_m = float(max_distance_m)
        self.version = 0
        self.origin: FloatArray = np.zeros(3)
        self._blocked: BoolArray = np.zeros((0, 0, 0), dtype=bool)
        # Padded by one cell.
        self._field: Float32Array = np.full((2, 2, 2), self._far, dtype=np.float32)
        self._anchor: FloatArray | None = None  # first origin: the lattice every grid sits on
        self._lo: Int64Array = np.zeros(3, dtype=np.int64)  # lattice index of cell (0, 0, 0)
        self._reach = reach_cells(self.voxel_m, self.max_distance_m)

    # --- construction ------------------------------------------------------------------------
    @classmethod
    def from_boxes(
        cls,
        bounds_min: ArrayLike,
        bounds_max: ArrayLike,
        boxes: Iterable[tuple[ArrayLike, ArrayLike]],
        voxel_m: float = 0.05,
        unknown_is_free: bool = False,
        max_distance_m: float = 1.0,
    ) -> FlightMap:
        """A map where everything inside ``bounds`` (metres) is observed and every cell that
        overlaps one of ``boxes`` (pairs of (3,) corners) is occupied. For tests and scenes."""
        lo = np.asarray(bounds_min, dtype=np.float64)
        cells = np.ceil((np.asarray(bounds_max, dtype=np.float64) - lo) / voxel_m - 1e-9)
        shape = tuple(int(n) for n in np.maximum(cells, 1))
        occupied = np.zeros(shape, dtype=bool)
        for box_lo, box_hi in boxes:
            # Cells whose open span overlaps the box's open interior.
            a = np.floor((np.asarray(box_lo) - lo) / voxel_m + 1e-9).astype(int)
            b = np.ceil((np.asarray(box_hi) - lo) / voxel_m - 1e-9).astype(int)
            occupied[slices(np.clip(a, 0, shape), np.clip(b, 0, shape))] = True
        flight_map = cls(voxel_m, unknown_is_free, max_distance_m)
        flight_map.update(lo, occupied, np.ones(shape, dtype=bool))
        return flight_map

    # --- properties --------------------------------------------------------------------------
    @property
    def _far(self) -> float:
        """The field's value far away from everything, which is outside state."""
        return self.max_distance_m if self.unknown_is_free else -self.max_distance_m

    @property
    def shape(self) -> tuple[int, ...]:
        """(X, Y, Z) cells."""
        return self._blocked.shape

    @property
    def blocked(self) -> BoolArray:
        """(X, Y, Z) bool, read-only view."""
        view: BoolArray = self._blocked.view()
        view.flags.writeable = False
        return view

    @property
    def esdf(self) -> Float32Array:
        """(X, Y, Z) float32 signed distance at cell centres (metres), read-only view."""
        view = self._field[1:-1, 1:-1, 1:-1]
        view.flags.writeable = False
        return view

    @property
    def bounds(self) -> Box:
        """The grid's extent in the flight frame."""
        return Box(self.origin.copy(), self.origin + np.array(self.shape) * self.voxel_m)

    def cell_centres(self, ijk: ArrayLike) -> FloatArray:
        """(N, 3) integer cell indices -> (N, 3) centres, metres."""
        return self.origin + (np.asarray(ijk, dtype=np.float64) + 0.5) * self.voxel_m

    # --- updates -----------------------------------------------------------------------------
    def update(self, origin: ArrayLike, occupied: ArrayLike, observed: ArrayLike) -> Box | None:
        """Replace the map with this grid and bring the distance field up to date.

        origin: (3,) corner of cell (0, 0, 0), metres; every grid after the first must sit on
        the same lattice (else the field is rebuilt). occupied, observed: (X, Y, Z) bool.
        Returns the region (metres) where the field may have changed: the cells whose blocked
        state changed, grown by ``max_distance_m``; None when no cell changed.
        """
        origin = np.asarray(origin, dtype=np.float64).reshape(-1)
        occupied, observed = np.asarray(occupied, dtype=bool), np.asarray(observed, dtype=bool)
        if origin.shape != (3,) or not np.all(np.isfinite(origin)):
            raise FlightMapError(f"origin must be 3 finite numbers, got {origin}")
        if occupied.ndim != 3 or occupied.shape != observed.shape:
            raise FlightMapError(
                f"occupied and observed must be (X, Y, Z) arrays of one shape, "
                f"got {occupied.shape} and {observed.shape}"
            )
        blocked = occupied if self.unknown_is_free else occupied | ~observed

        lo_new = self._lattice_index(origin)
        if self._anchor is None or lo_new is None:  # the first grid, or one off the lattice
            self._anchor = origin.copy()  # sets the lattice
            return self._rebuild(origin, np.zeros(3, dtype=np.int64), blocked)
        return self._update_incremental(self._anchor, origin, lo_new, blocked)

    def update_region(
        self,
        origin: ArrayLike,
        occupied: ArrayLike,
        observed: ArrayLike,
        written: ArrayLike | None = None,
    ) -> Box | None:
        """Overwrite a sub-box of the map and bring the distance field up to date around it.

        origin: (3,) corner of the sub-box's cell (0, 0, 0), metres, on the map's lattice (a
        whole number of cells from the first grid's origin; ``TSDFMap.occupancy_update`` gives
        such boxes). occupied, observed: (X, Y, Z) bool; written: (X, Y, Z) bool, the cells to
        overwrite (None: all), so that several coalesced boxes can go in as one. The grid grows
        to take the box in (the new cells unobserved); the rest of the map stays as it was. Only
        the field within ``max_distance_m`` of the cells whose blocked state changed is
        recomputed (the whole field when that is over half the grid); it equals a full rebuild
        of the merged grid. The first call on an empty map is ``update``. Returns what
        ``update`` returns.
        """
        origin = np.asarray(origin, dtype=np.float64).reshape(-1)
        occupied, observed = np.asarray(occupied, dtype=bool), np.asarray(observed, dtype=bool)
        written = np.ones(occupied.shape, bool) if written is None else np.asarray(written, bool)
        if occupied.ndim != 3 or not occupied.shape == observed.shape == written.shape:
            raise FlightMapError(
                f"occupied, observed and written must be (X, Y, Z) arrays of "
                f"one shape, got {occupied.shape}, {observed.shape} and "
                f"{written.shape}"
            )
        if self._anchor is None or 0 in self.shape:  # nothing to merge with
            return self.update(origin, occupied & written, observed & written)
        if origin.shape != (3,) or not np.all(np.isfinite(origin)):
            raise FlightMapError(f"origin must be 3 finite numbers, got {origin}")
        box_lo = self._lattice_index(origin)
        if box_lo is None:
            raise FlightMapError(f"sub-box origin {origin} is off the flight map's lattice")
        box_hi = box_lo + occupied.shape
        # The merged grid: the present one grown to take the box in, then the box written.
        lo, hi = np.minimum(self._lo, box_lo), np.maximum(self._lo + self.shape, box_hi)
        merged = np.full(hi - lo, not self.unknown_is_free)
        merged[slices(self._lo - lo, self._lo + self.shape - lo)] = self._blocked
        target = merged[slices(box_lo - lo, box_hi - lo)]
        blocked = occupied if self.unknown_is_free else occupied | ~observed
        target[written] = blocked[written]
        anchor = self._anchor
        return self._update_incremental(anchor, anchor + lo * self.voxel_m, lo, merged)

    def _lattice_index(self, origin: FloatArray) -> Int64Array | None:
        """The lattice index of the cell whose corner is ``origin`` (metres), or None when
        there is no lattice yet or ``origin`` is off it."""
        if self._anchor is None:
            return None
        steps = (origin - self._anchor) / self.voxel_m
        lo: Int64Array = np.round(steps).astype(np.int64)
        if np.any(np.abs(steps - lo) > _LATTICE_TOL):
            log.warning("grid origin %s is off the flight map's lattice: full rebuild", origin)
            return None
        return lo

    def _rebuild(self, origin: FloatArray, lo: Int64Array, blocked: BoolArray) -> Box:
        """Replace the grid by ``blocked`` (cell (0, 0, 0) at ``origin``, metres, and at
        lattice index ``lo``) and compute its whole field."""
        self.origin, self._lo, self._blocked = origin.copy(), lo, blocked.copy()
        ringed = padded(blocked, self.unknown_is_free)
        self._field = signed_distance(ringed, self.voxel_m, self.max_distance_m)
        self.version += 1
        return self.bounds

    def _update_incremental(
        self, anchor: FloatArray, origin: FloatArray, lo_new: Int64Array, blocked: BoolArray
    ) -> Box | None:
        """Replace the grid by ``blocked`` (cell (0, 0, 0) at ``origin``, metres, and at index
        ``lo_new`` of the lattice through ``anchor``), recomputing the field only near what
        changed (esdf.py: updated_field); returns the changed box as ``update`` does."""
        update = updated_field(
            self._lo,
            self._blocked,
            self._field,
            lo_new,
            blocked,
            self.voxel_m,
            self.max_distance_m,
            self.unknown_is_free,
        )
        if update is None:
            return None
        self.origin, self._lo, self._blocked = origin.copy(), lo_new, blocked.copy()
        self._field = update.field
        self.version += 1
        if update.changed is None:
            return None
        c_lo, c_hi = update.changed
        return Box(
            anchor + c_lo * self.voxel_m - self.max_distance_m,
            anchor + c_hi * self.voxel_m + self.max_distance_m,
        )

    # --- queries -----------------------------------------------------------------------------
    @overload
    def _interpolate(self, points: ArrayLike, want_gradient: Literal[False]) -> FloatArray: ...
    @overload
    def _interpolate(
        self, points: ArrayLike, want_gradient: Literal[True]
    ) -> tuple[FloatArray, FloatArray]: ...
    def _interpolate(
        self, points: ArrayLike, want_gradient: bool
    ) -> FloatArray | tuple[FloatArray, FloatArray]:
        """The trilinearly interpolated field at points (..., 3) (metres), shape (...), and
        with ``want_gradient`` its (..., 3) gradient too."""
        p = np.asarray(points, dtype=np.float64)
        flat = p.reshape(-1, 3)
        # Continuous index into the padded field: its cell 0 is the ring at -1.
        u = (flat - self.origin) / self.voxel_m + 0.5
        top = np.array(self._field.shape) - 1
        u = np.clip(u, 0.0, top)
        i0 = np.minimum(np.floor(u).astype(np.int64), top - 1)
        f = u - i0
        x, y, z = i0[:, 0], i0[:, 1], i0[:, 2]
        F = self._field
        c = np.empty((8, len(flat)), dtype=np.float64)
        for n, (a, b, d) in enumerate(np.ndindex(2, 2, 2)):
            c[n] = F[x + a, y + b, z + d]
        fx, fy, fz = f[:, 0], f[:, 1], f[:, 2]
        # c index n = 4a + 2b + d; interpolate along z, then y, then x.
        c00, c01 = c[0] + (c[1] - c[0]) * fz, c[2] + (c[3] - c[2]) * fz
        c10, c11 = c[4] + (c[5] - c[4]) * fz, c[6] + (c[7] - c[6]) * fz
        c0, c1 = c00 + (c01 - c00) * fy, c10 + (c11 - c10) * fy
        value: FloatArray = (c0 + (c1 - c0) * fx).reshape(p.shape[:-1])
        if not want_gradient:
            return value
        gx = c1 - c0
        gy = (c01 - c00) * (1 - fx) + (c11 - c10) * fx
        dz = [c[2 * m + 1] - c[2 * m] for m in range(4)]  # along z, at (a, b) = 00, 01, 10, 11
        gz = (dz[0] * (1 - fy) + dz[1] * fy) * (1 - fx) + (dz[2] * (1 - fy) + dz[3] * fy) * fx
        grad = np.stack([gx, gy, gz], axis=1) / self.voxel_m
        return value, grad.reshape(p.shape)

    def distance(self, points: ArrayLike) -> FloatArray:
        """Signed distance (metres) from points (..., 3) to the nearest blocked space: negative
        inside it, clipped to +-max_distance_m; points beyond the grid read as its outside."""
        return self._interpolate(points, want_gradient=False)

    def distance_at(self, x: float, y: float, z: float) -> float:
        """``distance`` of the one point (x, y, z) (metres), as a float: the same arithmetic
        in plain floats, for the physics loop's per-chunk query, where numpy's per-call cost
        would be most of it (``distance`` gives the same value, to the bit)."""
        F = self._field
        nx, ny, nz = F.shape
        ox, oy, oz = self.origin.tolist()
        v = self.voxel_m
        # As _interpolate: the continuous index, clipped to the padded field, and its cell.
        ux = (x - ox) / v + 0.5
        uy = (y - oy) / v + 0.5
        uz = (z - oz) / v + 0.5
        ux = 0.0 if ux < 0.0 else (float(nx - 1) if ux > nx - 1 else ux)
        uy = 0.0 if uy < 0.0 else (float(ny - 1) if uy > ny - 1 else uy)
        uz = 0.0 if uz < 0.0 else (float(nz - 1) if uz > nz - 1 else uz)
        i, j, k = (
            min(math.floor(ux), nx - 2),
            min(math.floor(uy), ny - 2),
            min(math.floor(uz), nz - 2),
        )
        fx, fy, fz = ux - i, uy - j, uz - k
        ((c000, c001), (c010, c011)), ((c100, c101), (c110, c111)) = F[
            i : i + 2, j : j + 2, k : k + 2
        ].tolist()
        c00, c01 = c000 + (c001 - c000) * fz, c010 + (c011 - c010) * fz
        c10, c11 = c100 + (c101 - c100) * fz, c110 + (c111 - c110) * fz
        c0, c1 = c00 + (c01 - c00) * fy, c10 + (c11 - c10) * fy
        value: float = c0 + (c1 - c0) * fx
        return value

    def gradient(self, points: ArrayLike) -> FloatArray:
        """(..., 3) gradient of ``distance`` (analytic, of the trilinear interpolation); it
        points away from the nearest obstacle, length about 1 (0 where the field is clipped)."""
        return self._interpolate(points, want_gradient=True)[1]

    def is_free(self, points: ArrayLike, radius_m: float = 0.0) -> BoolArray:
        """(...,) bool: a sphere of ``radius_m`` at each point clears every blocked cell."""
        return self.distance(points) >= radius_m

    def segment_clearance(self, a: ArrayLike, b: ArrayLike) -> float:
        """Least ``distance`` along the segment a-b ((3,) each, metres), sampled every half
        voxel or closer (ends included); ``segment_clearances`` checks many segments at once."""
        return float(self.segment_clearances(np.reshape(a, (1, 3)), np.reshape(b, (1, 3)))[0])

    def segment_clearances(self, a: ArrayLike, b: ArrayLike) -> FloatArray:
        """(M,) ``segment_clearance`` of each segment a[m]-b[m]; a, b: (M, 3), metres."""
        a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
        a, b = a.reshape(-1, 3), b.reshape(-1, 3)
        if len(a) == 0:
            return np.empty(0)
        lengths = np.linalg.norm(b - a, axis=1)
        counts = np.ceil(lengths / (0.5 * self.voxel_m)).astype(np.int64) + 1
        seg = np.repeat(np.arange(len(a)), counts)
        starts = np.cumsum(counts) - counts
        t = (np.arange(counts.sum()) - starts[seg]) / np.maximum(counts[seg] - 1, 1)
        least: FloatArray = np.minimum.reduceat(
            self.distance(a[seg] + (b - a)[seg] * t[:, None]), starts
        )
        return least

    def segment_is_free(self, a: ArrayLike, b: ArrayLike, radius_m: float = 0.0) -> bool:
        """Whether a sphere of ``radius_m`` swept from a to b ((3,) each, metres) stays free
        (``segment_clearance`` >= radius_m); ``segments_free`` checks many segments at once."""
        return self.segment_clearance(a, b) >= radius_m

    def segments_free(self, a: ArrayLike, b: ArrayLike, radius_m: float = 0.0) -> BoolArray:
        """(M,) bool ``segment_is_free`` of each segment a[m]-b[m]; a, b: (M, 3), metres."""
        return self.segment_clearances(a, b) >= radius_m

    def nearest_free(self, point: ArrayLike, radius_m: float = 0.0) -> FloatArray | None:
        """The cell centre nearest to ``point`` whose clearance is at least ``radius_m``, or None
        when there is none in the grid."""
        p = np.asarray(point, dtype=np.float64).reshape(3)
        if not np.all(np.isfinite(p)) or 0 in self.shape:
            return None
        esdf = self.esdf
        shape = np.array(self.shape)
        centre = np.clip(np.floor((p - self.origin) / self.voxel_m).astype(np.int64), 0, shape - 1)
        half = 4
        while True:  # grow a window around the point until the best find is provably nearest
            lo, hi = np.maximum(centre - half, 0), np.minimum(centre + half + 1, shape)
            cells = np.argwhere(esdf[slices(lo, hi)] >= radius_m) + lo
            whole = np.all(lo == 0) and np.all(hi == shape)
            if len(cells):
                centres = self.cell_centres(cells)
                d = np.linalg.norm(centres - p, axis=1)
                best = int(np.argmin(d))
                # Anything outside the window is farther than the window's inner half-width.
                inner = (half - 0.5) * self.voxel_m - np.max(np.abs(p - self.cell_centres(centre)))
                if whole or d[best] <= inner:
                    nearest: FloatArray = centres[best]
                    return nearest
            elif whole:
                return None
            half *= 2

    def random_free_points(self, n: int, radius_m: float, rng: np.random.Generator) -> FloatArray:
        """(n, 3) cell centres drawn uniformly among those with clearance >= ``radius_m``;
        (0, 3) when there are none."""
        cells = np.argwhere(self.esdf >= radius_m)
        if len(cells) == 0:
            return np.empty((0, 3))
        return self.cell_centres(cells[rng.integers(0, len(cells), size=n)])
