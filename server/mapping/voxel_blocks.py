"""The Open3D grid a TSDF map lives in (tensor ``VoxelBlockGrid``): its attributes per voxel, a
new grid, a grid holding given blocks, and its blocks read back as numpy arrays.

A grid is a hash map of blocks of ``block_resolution``^3 voxels, keyed by integer block
coordinates; per voxel it holds ``ATTRIBUTES``: a TSDF value (signed distance / truncation,
-1..1), a weight (observations) and an RGB colour (0..255), all float32. The callers
(``TSDFMap``, server/mapping/tsdf.py) hold the lock that guards a grid.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import numpy as np
import open3d as o3d
import open3d.core as o3c
from numpy.typing import NDArray

from server.geometry.arrays import BoolArray, Float32Array, Int64Array
from server.mapping.config import TSDFConfig

BYTES_PER_VOXEL = 4 * (1 + 1 + 3)  # float32 tsdf, weight, RGB
# The device numpy arrays become tensors on: Open3D's default, passed (with the dtype) because
# open3d's stubs declare no defaults for Tensor(np_array, dtype, device).
HOST = o3c.Device("CPU:0")

ATTRIBUTES = ("tsdf", "weight", "color")  # per voxel: signed distance, weight, RGB


def new_grid(config: TSDFConfig, block_count: int) -> o3d.t.geometry.VoxelBlockGrid:
    f32 = o3c.float32
    return o3d.t.geometry.VoxelBlockGrid(
        list(ATTRIBUTES),
        [f32, f32, f32],
        [o3c.SizeVector([1]), o3c.SizeVector([1]), o3c.SizeVector([3])],
        config.voxel_m,
        config.block_resolution,
        block_count,
        o3c.Device(config.device),
    )


def grid_from_blocks(
    config: TSDFConfig, keys: NDArray[np.int32], values: dict[str, Float32Array]
) -> o3d.t.geometry.VoxelBlockGrid:
    """A grid holding the given blocks: keys (N, 3) block coordinates, values per attribute
    (N, R, R, R, channels), on the CPU (``load`` moves it to the configured device)."""
    n = len(keys)
    r = config.block_resolution
    for name, channels in zip(ATTRIBUTES, (1, 1, 3), strict=True):
        if values[name].shape != (n, r, r, r, channels):
            raise ValueError(
                f"map {name} has shape {values[name].shape}, not {(n, r, r, r, channels)}"
            )
    grid = new_grid(replace(config, device="CPU:0"), max(config.block_count, n))
    if n == 0:
        return grid
    coords = o3c.Tensor(np.ascontiguousarray(keys, np.int32), o3c.int32, HOST)
    buf, _ = grid.hashmap().activate(coords)
    index = buf.to(o3c.int64).numpy()
    for name in ATTRIBUTES:
        grid.attribute(name).numpy()[index] = values[name]  # a view of the grid's own buffer
    return grid


def active_keys(grid: o3d.t.geometry.VoxelBlockGrid) -> NDArray[np.int32]:
    """(B, 3) integer keys of the grid's allocated blocks (Open3D keeps them as int32)."""
    hashmap = grid.hashmap()
    idx = hashmap.active_buf_indices().to(o3c.int64)
    keys: NDArray[np.int32] = hashmap.key_tensor()[idx].cpu().numpy().reshape(-1, 3)
    return keys


def read_blocks(
    grid: o3d.t.geometry.VoxelBlockGrid, select: Callable[[Int64Array], BoolArray] | None = None
) -> tuple[Int64Array, Float32Array, Float32Array]:
    """Keys (B, 3) of the grid's active blocks (those ``select(keys)`` -> (N,) bool keeps), and
    copies of their tsdf and weight (B, z, y, x). Call with the grid's lock held."""
    hashmap = grid.hashmap()
    idx = hashmap.active_buf_indices().cpu().numpy().astype(np.int64)
    keys = hashmap.key_tensor().cpu().numpy()[idx].astype(np.int64).reshape(-1, 3)
    if select is not None:
        keep = select(keys)
        idx, keys = idx[keep], keys[keep]
    # .numpy() views the grid's memory; fancy indexing copies it while the lock is held
    # (Open3D's own tensor indexing is ~20x slower here).
    tsdf: Float32Array = grid.attribute("tsdf").numpy()[idx, ..., 0]
    weight: Float32Array = grid.attribute("weight").numpy()[idx, ..., 0]
    return keys, tsdf, weight
