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
BYTES_PER_FREE_VOXEL = 4 * (1 + 1)  # float32 tsdf, weight
# The device numpy arrays become tensors on: Open3D's default, passed (with the dtype) because
# open3d's stubs declare no defaults for Tensor(np_array, dtype, device).
HOST = o3c.Device("CPU:0")

ATTRIBUTES = ("tsdf", "weight", "color")  # per voxel: signed distance, weight, RGB
FREE_ATTRIBUTES = ("tsdf", "weight")  # the free-space grid's (server/mapping/free_space.py)
CHANNELS = {"tsdf": 1, "weight": 1, "color": 3}


def new_grid(
    config: TSDFConfig, block_count: int, attributes: tuple[str, ...] = ATTRIBUTES
) -> o3d.t.geometry.VoxelBlockGrid:
    return o3d.t.geometry.VoxelBlockGrid(
        list(attributes),
        [o3c.float32] * len(attributes),
        [o3c.SizeVector([CHANNELS[name]]) for name in attributes],
        config.voxel_m,
        config.block_resolution,
        block_count,
        o3c.Device(config.device),
    )


def grid_from_blocks(
    config: TSDFConfig,
    keys: NDArray[np.int32],
    values: dict[str, Float32Array],
    attributes: tuple[str, ...] = ATTRIBUTES,
) -> o3d.t.geometry.VoxelBlockGrid:
    """A grid holding the given blocks: keys (N, 3) block coordinates, values per attribute
    (N, R, R, R, channels), on the CPU (``load`` moves it to the configured device)."""
    n = len(keys)
    r = config.block_resolution
    for name in attributes:
        if values[name].shape != (n, r, r, r, CHANNELS[name]):
            raise ValueError(
                f"map {name} has shape {values[name].shape}, not {(n, r, r, r, CHANNELS[name])}"
            )
    grid = new_grid(replace(config, device="CPU:0"), max(config.block_count, n), attributes)
    if n == 0:
        return grid
    coords = o3c.Tensor(np.ascontiguousarray(keys, np.int32), o3c.int32, HOST)
    buf, _ = grid.hashmap().activate(coords)
    index = buf.to(o3c.int64).numpy()
    for name in attributes:
        grid.attribute(name).numpy()[index] = values[name]  # a view of the grid's own buffer
    return grid


def reblocked(
    keys: NDArray[np.integer], values: dict[str, Float32Array], resolution: int
) -> tuple[NDArray[np.int32], dict[str, Float32Array]]:
    """The same voxels in blocks of ``resolution``^3: keys (N, 3) and values (N, R, R, R, c)
    per attribute (axes z, y, x within a block) in blocks of R^3, one resolution a multiple of
    the other. A block of the new size none of whose voxels was seen (weight 0) is left out.
    ValueError when neither divides the other."""
    keys = np.asarray(keys, np.int64).reshape(-1, 3)
    old = values["weight"].shape[1]
    if old == resolution:
        return keys.astype(np.int32), values
    if len(keys) == 0:
        r = resolution
        return keys.astype(np.int32), {
            k: np.zeros((0, r, r, r, v.shape[-1]), v.dtype) for k, v in values.items()
        }
    if old % resolution == 0:  # split each block into f^3
        f, r = old // resolution, resolution
        offsets = np.stack(np.meshgrid(*[np.arange(f)] * 3, indexing="ij"), -1).reshape(-1, 3)
        # offsets as (z, y, x) in the order the split values come; keys are (x, y, z).
        new_keys = (keys[:, None, :] * f + offsets[None, :, ::-1]).reshape(-1, 3)
        split = {
            name: v.reshape(len(keys), f, r, f, r, f, r, -1)
            .transpose(0, 1, 3, 5, 2, 4, 6, 7)
            .reshape(-1, r, r, r, v.shape[-1])
            for name, v in values.items()
        }
    elif resolution % old == 0:  # f^3 blocks into one
        f, r = resolution // old, old
        merged_keys, index = np.unique(np.floor_divide(keys, f), axis=0, return_inverse=True)
        z, y, x = (keys - merged_keys[index] * f).T[::-1]
        split = {}
        for name, v in values.items():
            out = np.zeros((len(merged_keys), f, r, f, r, f, r, v.shape[-1]), v.dtype)
            out[index, z, :, y, :, x, :] = v
            split[name] = out.reshape(len(merged_keys), resolution, resolution, resolution, -1)
        new_keys = merged_keys
    else:
        raise ValueError(f"cannot re-block {old}^3 blocks into {resolution}^3")
    seen = split["weight"].reshape(len(new_keys), -1).max(axis=1) > 0
    return new_keys[seen].astype(np.int32), {name: v[seen] for name, v in split.items()}


def active_keys(grid: o3d.t.geometry.VoxelBlockGrid) -> NDArray[np.int32]:
    """(B, 3) integer keys of the grid's allocated blocks (Open3D keeps them as int32)."""
    hashmap = grid.hashmap()
    idx = hashmap.active_buf_indices().to(o3c.int64)
    keys: NDArray[np.int32] = hashmap.key_tensor()[idx].cpu().numpy().reshape(-1, 3)
    return keys


def read_all(
    grid: o3d.t.geometry.VoxelBlockGrid, attributes: tuple[str, ...] = ATTRIBUTES
) -> tuple[NDArray[np.int32], dict[str, Float32Array]]:
    """Keys (B, 3) of the grid's active blocks and copies of their values per attribute
    (B, R, R, R, channels). Call with the grid's lock held."""
    hashmap = grid.hashmap()
    active = hashmap.active_buf_indices().to(o3c.int64).numpy()
    keys: NDArray[np.int32] = hashmap.key_tensor().numpy()[active].reshape(-1, 3)
    return keys, {name: grid.attribute(name).numpy()[active] for name in attributes}


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


def has_surface(grid: o3d.t.geometry.VoxelBlockGrid, min_weight: float) -> bool:
    """Whether marching cubes (``extract_triangle_mesh(min_weight)``) finds a surface: voxels
    observed more than ``min_weight`` times (Open3D skips those of weight <= it) on both sides
    of one. Reads the grid a thousand blocks at a time until it knows: all of a map that has
    none yet (its first frames: small), the first blocks of one that has (a rebuilt room).
    Call with the grid's lock held."""
    hashmap = grid.hashmap()
    if hashmap.size() == 0:
        return False
    idx = hashmap.active_buf_indices().cpu().numpy().astype(np.int64)
    weight, tsdf = grid.attribute("weight").numpy(), grid.attribute("tsdf").numpy()
    inside = outside = False
    for start in range(0, len(idx), 1024):
        blocks = idx[start : start + 1024]
        values = tsdf[blocks, ..., 0][weight[blocks, ..., 0] > min_weight]
        inside = inside or bool((values < 0).any())
        outside = outside or bool((values > 0).any())
        if inside and outside:
            return True
    return False
