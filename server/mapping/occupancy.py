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
    if R is None:
        return p
    R = np.asarray(R, dtype=np.float64)
    return np.stack(
        [p[:, 0] * R[i, 0] + p[:, 1] * R[i, 1] + p[:, 2] * R[i, 2] for i in range(3)], axis=1
    )


def camera_cells(cameras: FloatArray, voxel_m: float, R_grid_world: RealArray | None) -> Int64Array:
    """Grid cells (C, 3) of camera positions (world (C, 3), metres)."""
    return np.floor(rotate(cameras, R_grid_world) / voxel_m).astype(np.int64)


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
) -> Int64Array:
    """Cells of the voxels at ``voxels`` = (block, z, y, x) indices, into blocks sampled at
    every step-th voxel."""
    b, zl, yl, xl = voxels
    local = np.stack([xl, yl, zl], axis=1) * step
    world = (keys[b] * cfg.block_resolution + local).astype(np.float32) * cfg.voxel_m
    return np.floor(rotate(world, R_grid_world) / voxel_m).astype(np.int64)


def seen_cells(
    keys: Int64Array,
    weight: Float32Array,
    voxel_m: float,
    R_grid_world: RealArray | None,
    cfg: TSDFConfig,
) -> Int64Array:
    """Grid cells (integer (N, 3), not unique) of the given blocks' seen voxels (weight > 0),
    blocks of ``cfg``'s voxels: every s-th voxel each way is enough to say what was seen, as
    long as samples stay closer than a cell."""
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
) -> tuple[Int64Array, Int64Array]:
    """Grid cells (integer (N, 3) each, not unique) of the given blocks' seen voxels and of
    their surface voxels."""
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


def grid_of(
    observed_cells: Int64Array, surface_cells: Int64Array, voxel_m: float
) -> tuple[FloatArray, BoolArray, BoolArray] | None:
    """(origin, occupied, observed) of the box the observed cells span (surface cells within
    it), or None when there are none."""
    if observed_cells.size == 0:
        return None
    lo, hi = observed_cells.min(axis=0), observed_cells.max(axis=0) + 1
    observed: BoolArray = np.zeros(tuple(hi - lo), dtype=bool)
    occupied = np.zeros_like(observed)
    observed[tuple((observed_cells - lo).T)] = True
    occupied[tuple((surface_cells - lo).T)] = True
    # np.float64: numpy's stubs type an int64 array times a float as of any float precision.
    return lo * np.float64(voxel_m), occupied, observed


def in_box(cells: Int64Array, box_lo: Int64Array, box_hi: Int64Array) -> Int64Array:
    """The cells (N, 3) inside [box_lo, box_hi)."""
    # One unsigned comparison per axis: below box_lo wraps to above any size.
    inside = (cells - box_lo).astype(np.uint64) < (box_hi - box_lo).astype(np.uint64)
    return cells[inside[:, 0] & inside[:, 1] & inside[:, 2]]
