"""A coarse occupancy grid from TSDF blocks, for the drone simulator (``TSDFMap.occupancy``),
and the free space that fusion carves so that the grid can tell free space from unknown.

Pure functions on what ``TSDFMap`` reads from its grid under its lock: block keys (B, 3) (integer
block coordinates), their TSDF values and weights (B, z, y, x), and the fused cameras' positions
(world, metres). Grid cells are ``voxel_m`` cubes in the frame ``R_grid_world`` (3x3) rotates the
world into (None: the world's own axes), indexed by integer (i, j, k) = floor(position / voxel_m).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from server.errors import ConfigError
from server.geometry import Intrinsics
from server.geometry.arrays import (
    BoolArray,
    Float32Array,
    FloatArray,
    IndexArray,
    Int64Array,
    RealArray,
)
from server.mapping.config import TSDFConfig

_CARVE_STRIDE_PX = 16  # one free-space ray per 16 x 16 depth pixels
_KEY_BIAS = 1 << 20  # integer keys packed in one int64: 21 bits per axis


def pack_keys(ijk: ArrayLike) -> Int64Array:
    """Integer 3D keys (N, 3) (each within +-2^20) -> one sortable int64 each."""
    k = np.asarray(ijk, dtype=np.int64) + _KEY_BIAS
    return (k[:, 0] << 42) | (k[:, 1] << 21) | k[:, 2]


def unpack_keys(keys: Int64Array) -> Int64Array:
    """Inverse of ``pack_keys``: (N,) keys -> (N, 3) integer keys."""
    mask = (1 << 21) - 1
    return np.stack([keys >> 42, (keys >> 21) & mask, keys & mask], axis=1) - _KEY_BIAS


def free_space_keys(
    depth: Float32Array, K: Intrinsics, T: FloatArray, cfg: TSDFConfig
) -> Int64Array:
    """Packed keys of the blocks of ``cfg``'s geometry that sparse rays of a frame (depth
    (H, W), metres, seen with K from T_world_camera ``T``) cross between the camera and the
    surface band."""
    s = _CARVE_STRIDE_PX
    d = depth[s // 2 :: s, s // 2 :: s]
    v, u = np.nonzero((d > 0) & (d <= cfg.depth_max_m))
    z = d[v, u]
    # Ray direction scaled to unit depth, so that a point at depth t is rays * t.
    rays = np.stack(
        [
            (u * s + s // 2 - K.cx) / K.fx,
            (v * s + s // 2 - K.cy) / K.fy,
            np.ones_like(z, dtype=np.float64),
        ],
        axis=1,
    )
    t = np.arange(0.0, cfg.depth_max_m, cfg.block_m / 2)
    r, c = np.nonzero(t[None, :] < z[:, None] - cfg.trunc_m)
    world = (rays[r] * t[c, None]) @ T[:3, :3].T + T[:3, 3]
    return np.unique(pack_keys(np.floor(world / cfg.block_m)))


def check_cell(voxel_m: float) -> None:
    if not voxel_m > 0:
        raise ConfigError(f"occupancy voxel size must be positive, got {voxel_m}")


def rotate(points: ArrayLike, R: RealArray | None) -> FloatArray:
    """(N, 3) points (float64) rotated by R (3x3; None: unrotated). Written out per element, not
    as a matrix product, so that a point's result does not depend on how many points are rotated
    with it (a BLAS product may round differently by batch): occupancy_update then finds the
    very cells a full occupancy does."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    return np.stack(_rotated(p[:, 0], p[:, 1], p[:, 2], R), axis=1)


def _rotated(
    x: FloatArray, y: FloatArray, z: FloatArray, R: RealArray | None
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Points given per axis (float64, N each) rotated by R (None: as they are), per element."""
    if R is None:
        return x, y, z
    R = np.asarray(R, dtype=np.float64)
    rx, ry, rz = (x * R[i, 0] + y * R[i, 1] + z * R[i, 2] for i in range(3))
    return rx, ry, rz


# Grid cells as one integer array per axis (N each): the columns of an (N, 3) array, which
# numpy reduces and compares several times faster than the array's strided columns.
Cells = tuple[Int64Array, Int64Array, Int64Array]


def _floor_cells(x: FloatArray, y: FloatArray, z: FloatArray, voxel_m: float) -> Cells:
    cx, cy, cz = (np.floor(a / voxel_m).astype(np.int64) for a in (x, y, z))
    return cx, cy, cz


def camera_cells(cameras: FloatArray, voxel_m: float, R_grid_world: RealArray | None) -> Cells:
    """Grid cells of camera positions (world (C, 3), metres)."""
    p = np.asarray(cameras, dtype=np.float64).reshape(-1, 3)
    return _floor_cells(*_rotated(p[:, 0], p[:, 1], p[:, 2], R_grid_world), voxel_m)


def block_cells(
    keys: Int64Array, voxel_m: float, R_grid_world: RealArray | None, cfg: TSDFConfig
) -> tuple[Int64Array, Int64Array]:
    """(lo, hi), (B, 3) int64 each: the range of grid cells (inclusive) the voxels of each
    block (keys (B, 3)) can fall in, one cell wider each side than the blocks' corners
    say, for the float32 rounding of voxel positions in ``voxel_cells``."""
    res = cfg.block_resolution
    corners = np.array(np.meshgrid(*[[0, res - 1]] * 3, indexing="ij")).reshape(3, 8).T
    points = ((keys[:, None, :] * res + corners) * cfg.voxel_m).reshape(-1, 3)
    cells = np.floor(rotate(points, R_grid_world) / voxel_m).reshape(-1, 8, 3)
    return cells.min(axis=1).astype(np.int64) - 1, cells.max(axis=1).astype(np.int64) + 1


def _cells(
    keys: Int64Array,
    voxels: tuple[IndexArray, ...],
    step: int,
    voxel_m: float,
    R_grid_world: RealArray | None,
    cfg: TSDFConfig,
) -> Cells:
    """Cells of the voxels at ``voxels`` = (block, z, y, x) indices, into blocks sampled at
    every step-th voxel."""
    b, zl, yl, xl = voxels
    res = cfg.block_resolution
    # A voxel's position in float32, as the TSDF's own, then rotated in float64.
    x, y, z = (
        ((keys[b, axis] * res + local * step).astype(np.float32) * cfg.voxel_m).astype(np.float64)
        for axis, local in enumerate((xl, yl, zl))
    )
    return _floor_cells(*_rotated(x, y, z, R_grid_world), voxel_m)


def seen_cells(
    keys: Int64Array,
    weight: Float32Array,
    voxel_m: float,
    R_grid_world: RealArray | None,
    cfg: TSDFConfig,
) -> Cells:
    """Grid cells (not unique) of the given blocks' seen voxels (weight > 0), blocks of
    ``cfg``'s voxels: every s-th voxel each way is enough to say what was seen, as long as
    samples stay closer than a cell."""
    s = 1
    while s < cfg.block_resolution and 2 * s * cfg.voxel_m * 1.25 <= voxel_m:
        s *= 2
    return _cells(keys, np.nonzero(weight[:, ::s, ::s, ::s] > 0), s, voxel_m, R_grid_world, cfg)


def voxel_cells(
    keys: Int64Array,
    tsdf: Float32Array,
    weight: Float32Array,
    voxel_m: float,
    R_grid_world: RealArray | None,
    cfg: TSDFConfig,
) -> tuple[Cells, Cells]:
    """Grid cells (not unique) of the given blocks' seen voxels and of their surface voxels."""
    # Half the cell's diagonal: the projective TSDF overstates distances seen obliquely
    # (distance / cos of the view angle), and half the cell's edge left ~20% of surfaces out.
    band = min(max(0.87 * voxel_m, cfg.voxel_m), 0.99 * cfg.trunc_m)
    # Surfaces (a thin band) are placed from every voxel of the band.
    near = np.nonzero((np.abs(tsdf) < _stored_safe(band / cfg.trunc_m)) & (weight > 0))
    surface = _cells(keys, near, 1, voxel_m, R_grid_world, cfg)
    return seen_cells(keys, weight, voxel_m, R_grid_world, cfg), surface


def _stored_safe(limit: float) -> np.float32:
    """The midpoint of the two float16 values around ``limit``: a TSDF value is below it
    exactly when its float16 rounding is (save and load keep a map's TSDF as float16,
    server/mapping/tsdf_files.py), so a map loaded back has the very occupancy it had."""
    low = np.float16(limit)
    if low > limit:
        low = np.nextafter(low, np.float16(0))
    high = np.nextafter(low, np.float16(np.inf))
    mid: np.float32 = np.float32((float(low) + float(high)) / 2)
    return mid


class OccupancyBox:
    """A box of grid cells [lo, hi) (integer, per axis) in which cells are marked observed, and
    occupied; ``grid`` crops it to the observed ones. Cells outside the box are left out."""

    def __init__(self, lo: ArrayLike, hi: ArrayLike) -> None:
        self.lo = np.asarray(lo, dtype=np.int64).reshape(3)
        shape = np.maximum(np.asarray(hi, dtype=np.int64).reshape(3) - self.lo, 0)
        self.observed: BoolArray = np.zeros(tuple(int(n) for n in shape), dtype=bool)
        self.occupied: BoolArray = np.zeros_like(self.observed)

    @classmethod
    def around(cls, cell_sets: list[Cells]) -> OccupancyBox:
        """The smallest box holding every cell of ``cell_sets``."""
        lo, hi = np.zeros(3, np.int64), np.zeros(3, np.int64)
        filled = [cells for cells in cell_sets if len(cells[0])]
        for axis in range(3) if filled else ():
            lo[axis] = min(int(cells[axis].min()) for cells in filled)
            hi[axis] = max(int(cells[axis].max()) for cells in filled) + 1
        return cls(lo, hi)

    def mark(self, cells: Cells, occupied: bool = False) -> None:
        """Mark ``cells`` observed (and ``occupied``), those inside the box."""
        n = self.observed.shape
        offset = [c - lo for c, lo in zip(cells, self.lo, strict=True)]
        # One unsigned comparison per axis: below the box wraps to above any size.
        inside = offset[0].astype(np.uint64) < n[0]
        inside &= offset[1].astype(np.uint64) < n[1]
        inside &= offset[2].astype(np.uint64) < n[2]
        flat = (offset[0][inside] * n[1] + offset[1][inside]) * n[2] + offset[2][inside]
        self.observed.reshape(-1)[flat] = True
        if occupied:
            self.occupied.reshape(-1)[flat] = True

    def grid(self, voxel_m: float) -> tuple[FloatArray, BoolArray, BoolArray] | None:
        """(origin, occupied, observed) of the part of the box its observed cells span, or None
        when none is."""
        spans = []
        for axis in range(3):
            others = tuple(a for a in range(3) if a != axis)
            hit = np.flatnonzero(self.observed.any(axis=others))
            if len(hit) == 0:
                return None
            spans.append(slice(int(hit[0]), int(hit[-1]) + 1))
        lo = self.lo + [s.start for s in spans]
        crop = tuple(spans)
        # np.float64: numpy's stubs type an int64 array times a float as of any float precision.
        return (
            lo * np.float64(voxel_m),
            np.ascontiguousarray(self.occupied[crop]),
            np.ascontiguousarray(self.observed[crop]),
        )


def grid_in(
    box: OccupancyBox, voxel_m: float, observed: list[Cells], surface: Cells
) -> tuple[FloatArray, BoolArray, BoolArray] | None:
    """(origin, occupied, observed) within ``box`` (``OccupancyBox.grid``): the cells of every set
    of ``observed`` and of ``surface`` observed, those of ``surface`` occupied."""
    for cells in observed:
        box.mark(cells)
    box.mark(surface, occupied=True)
    return box.grid(voxel_m)
