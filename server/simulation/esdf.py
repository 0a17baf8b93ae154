"""The flight map's distance field (ESDF): computed whole, or again only around what changed.

Cells are indexed on one lattice (the flight map's: its first grid's origin); a grid is stored
with a one-cell ring around it holding the "outside" state (blocked unless ``unknown_is_free``).
The field at a cell centre is the distance between its centre and the nearest blocked (for a
free cell) or free (for a blocked cell) cell's centre, minus half a voxel, negative inside
blocked space, clipped to +-``max_distance_m`` (flight_map.py says why). The ring makes the
field exactly that of the infinite lattice, so a change recomputes only a window within
``max_distance_m`` of the cells whose state changed (``updated_field``), and the result equals
a full rebuild exactly.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TypeAlias

import edt
import numpy as np
from numpy.typing import NDArray

from server.geometry.arrays import BoolArray, Float32Array, Int64Array

REBUILD_FRACTION = 0.5  # a changed region above this share of the grid triggers a full rebuild


def slices(lo: NDArray[np.integer], hi: NDArray[np.integer]) -> tuple[slice, slice, slice]:
    """Index of the cells [lo, hi) ((3,) integer corners, hi exclusive) of a 3D array."""
    return (
        slice(int(lo[0]), int(hi[0])),
        slice(int(lo[1]), int(hi[1])),
        slice(int(lo[2]), int(hi[2])),
    )


CellBox: TypeAlias = tuple[Int64Array, Int64Array]
"""An integer box of cells: (lo, hi), (3,) each, hi exclusive."""


def _volume(box: CellBox) -> int:
    return int(np.prod(np.maximum(box[1] - box[0], 0)))


def _bbox(mask: BoolArray) -> CellBox | None:
    """The integer box (lo, hi) of a mask's True cells, or None."""
    spans = []
    for axis in range(3):
        hit = np.flatnonzero(np.any(mask, axis=tuple(a for a in range(3) if a != axis)))
        if hit.size == 0:
            return None
        spans.append((hit[0], hit[-1] + 1))
    lo = np.array([a for a, _ in spans], dtype=np.int64)
    hi = np.array([b for _, b in spans], dtype=np.int64)
    return lo, hi


def _intersect(a: CellBox, b: CellBox) -> CellBox:
    return np.maximum(a[0], b[0]), np.minimum(a[1], b[1])


def _subtract(a: CellBox, b: CellBox) -> list[CellBox]:
    """Disjoint boxes covering box a minus box b (at most six slabs)."""
    lo, hi = np.array(a[0]), np.array(a[1])
    pieces = []
    for axis in range(3):
        if lo[axis] < b[0][axis]:  # slab below b along this axis
            top = hi.copy()
            top[axis] = min(hi[axis], b[0][axis])
            pieces.append((lo.copy(), top))
            lo[axis] = min(hi[axis], b[0][axis])
        if hi[axis] > b[1][axis]:  # slab above
            bottom = lo.copy()
            bottom[axis] = max(lo[axis], b[1][axis])
            pieces.append((bottom, hi.copy()))
            hi[axis] = max(lo[axis], b[1][axis])
    return [p for p in pieces if _volume(p)]


def reach_cells(voxel_m: float, max_distance_m: float) -> int:
    """How many cells away a change of one cell's state can change the field."""
    return math.ceil(max_distance_m / voxel_m) + 1


def padded(blocked: BoolArray, unknown_is_free: bool) -> BoolArray:
    """``blocked`` with the ring of outside state around it."""
    return np.pad(blocked, 1, constant_values=not unknown_is_free)


def signed_distance(blocked: BoolArray, voxel_m: float, max_distance_m: float) -> Float32Array:
    """Clipped signed distance at cell centres of a whole (padded) block, float32, metres."""
    v, d = voxel_m, max_distance_m
    field = np.full(blocked.shape, d, dtype=np.float32)
    if blocked.any() and not blocked.all():  # edt has no answer without a zero
        # The edt package's exact transform: scipy.ndimage's, float32, in half the time.
        outside = edt.edt(~blocked, black_border=False, parallel=1)  # free -> nearest blocked
        inside = edt.edt(blocked, black_border=False, parallel=1)  # blocked -> nearest free
        field = np.where(blocked, -(inside - 0.5) * v, (outside - 0.5) * v)
    elif blocked.all():
        field[...] = -d
    return np.clip(field, -d, d).astype(np.float32)


@dataclass(frozen=True)
class FieldUpdate:
    """A grid's new field: ``field`` the padded field, float32, metres; ``changed`` the cells
    whose blocked state changed (lattice indices (lo, hi), hi exclusive), or None."""

    field: Float32Array
    changed: CellBox | None


def updated_field(
    old_lo: Int64Array,
    old_blocked: BoolArray,
    old_field: Float32Array,
    new_lo: Int64Array,
    new_blocked: BoolArray,
    voxel_m: float,
    max_distance_m: float,
    unknown_is_free: bool,
) -> FieldUpdate | None:
    """The field of ``new_blocked`` (its cell (0, 0, 0) at lattice index ``new_lo``) from the
    field ``old_field`` (padded) of ``old_blocked`` (at ``old_lo``), recomputed only near what
    changed (the whole field when that is over REBUILD_FRACTION of the grid); None when the
    grids are the same."""
    k = reach_cells(voxel_m, max_distance_m)
    outside = not unknown_is_free
    far = max_distance_m if unknown_is_free else -max_distance_m  # outside state's field
    old_hi, new_hi = old_lo + old_blocked.shape, new_lo + new_blocked.shape
    # A union frame holding both padded grids; everything else has outside state.
    u_lo = np.minimum(old_lo, new_lo) - 1
    u_hi = np.maximum(old_hi, new_hi) + 1
    old_u = np.full(u_hi - u_lo, outside)
    new_u = np.full(u_hi - u_lo, outside)
    old_u[slices(old_lo - u_lo, old_hi - u_lo)] = old_blocked
    new_u[slices(new_lo - u_lo, new_hi - u_lo)] = new_blocked
    changed = _bbox(old_u != new_u)
    same_frame = np.array_equal(old_lo, new_lo) and old_blocked.shape == new_blocked.shape
    if changed is None and same_frame:
        return None
    changed_cells = None if changed is None else (changed[0] + u_lo, changed[1] + u_lo)

    # Regions to recompute (union coordinates, clipped to the new padded grid): around the
    # changed cells, and the cells of the new padded grid the old one did not store but
    # close enough to the old grid that their field is not simply the far value.
    p_lo, p_hi = new_lo - 1 - u_lo, new_hi + 1 - u_lo
    regions: list[CellBox] = []
    if changed is not None:
        regions.append((changed[0] - k, changed[1] + k))
    near_old = (old_lo - k - u_lo, old_hi + k - u_lo)
    for box in _subtract((p_lo, p_hi), (old_lo - 1 - u_lo, old_hi + 1 - u_lo)):
        regions.append(_intersect(box, near_old))
    regions = [b for b in (_intersect(r, (p_lo, p_hi)) for r in regions) if _volume(b)]
    if sum(_volume(b) for b in regions) > REBUILD_FRACTION * _volume((p_lo, p_hi)):
        whole = signed_distance(padded(new_blocked, unknown_is_free), voxel_m, max_distance_m)
        return FieldUpdate(whole, changed_cells)

    # Old field carried into the new padded frame, far value where it was not stored.
    field = np.full(p_hi - p_lo, far, dtype=np.float32)
    ov_lo = np.maximum(old_lo - 1, new_lo - 1)
    ov_hi = np.minimum(old_hi + 1, new_hi + 1)
    if np.all(ov_hi > ov_lo):
        field[slices(ov_lo - new_lo + 1, ov_hi - new_lo + 1)] = old_field[
            slices(ov_lo - old_lo + 1, ov_hi - old_lo + 1)
        ]
    for r_lo, r_hi in regions:
        # Recompute the region from a window grown by the reach (nothing farther matters).
        w_lo, w_hi = np.maximum(r_lo - k, p_lo), np.minimum(r_hi + k, p_hi)
        window = signed_distance(new_u[slices(w_lo, w_hi)], voxel_m, max_distance_m)
        field[slices(r_lo - p_lo, r_hi - p_lo)] = window[slices(r_lo - w_lo, r_hi - w_lo)]
    return FieldUpdate(field, changed_cells)
