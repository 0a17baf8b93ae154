"""The free space a map's frames saw, for the drone's occupancy grid: a grid of its own beside the
TSDF, coarser and without colour (``TSDFConfig.carve_voxels`` TSDF voxels to an edge, 4 cm at
the defaults).

The drone tells free space from unknown by what was seen: a voxel with weight > 0. The TSDF
records that only near surfaces, so every ``carve_every``-th frame the blocks that sparse camera
rays cross before the surface (``occupancy.free_space_keys``) are integrated here too: Open3D
projects each voxel of those blocks into the depth image and marks it seen when a measurement
lies beyond it (or within the truncation behind it). Integrating them into the TSDF itself, as
before issue 34, cost nearly as much as fusing the surfaces did (every voxel of every crossed
block, at 2 cm, with colour: 12 of a carving frame's 26 ms on 7scenes_a), made a third of the
map's blocks, and bought nothing the occupancy grid reads: for 5 cm cells it samples every
second TSDF voxel each way (``occupancy.seen_cells``), the very points of this grid at 4 cm
(voxel j here sits where TSDF voxel 2j does, and sees the same distance).

Not thread-safe: ``TSDFMap`` holds its lock around every call.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import numpy as np
import open3d as o3d
import open3d.core as o3c
from numpy.typing import NDArray

from server.geometry.arrays import BoolArray, Float32Array, FloatArray, Int64Array
from server.mapping.config import TSDFConfig
from server.mapping.frame_input import FusionFrame, open3d_projection
from server.mapping.occupancy import free_space_keys, pack_keys, unpack_keys
from server.mapping.voxel_blocks import (
    BYTES_PER_FREE_VOXEL,
    FREE_ATTRIBUTES,
    HOST,
    active_keys,
    grid_from_blocks,
    new_grid,
    read_all,
    read_blocks,
    reblocked,
)

_BLOCK_COUNT = 64  # blocks allocated up front (4 KiB each at the defaults); doubles when full


def free_space_config(cfg: TSDFConfig) -> TSDFConfig:
    """The free-space grid's geometry: voxels ``carve_voxels`` times the TSDF's, the same
    truncation and range in metres, blocks of as many voxels."""
    f = cfg.carve_voxels
    return replace(
        cfg, voxel_m=cfg.voxel_m * f, trunc_voxels=cfg.trunc_voxels / f, block_count=_BLOCK_COUNT
    )


class FreeSpace:
    """The seen voxels (weight > 0) of the space carved so far, and which blocks changed since
    ``take_dirty``."""

    def __init__(self, tsdf: TSDFConfig, grid: o3d.t.geometry.VoxelBlockGrid | None = None):
        self.config = cfg = free_space_config(tsdf)
        self._device = o3c.Device(cfg.device)
        self._grid = grid if grid is not None else new_grid(cfg, cfg.block_count, FREE_ATTRIBUTES)
        self._dirty = np.sort(pack_keys(active_keys(self._grid)))

    @classmethod
    def from_blocks(
        cls,
        tsdf: TSDFConfig,
        voxel_m: float,
        keys: NDArray[np.int32],
        values: dict[str, Float32Array],
    ) -> FreeSpace | None:
        """The grid a map file stored (voxels of ``voxel_m``, any block resolution that
        divides or is divided by this one's); None when its voxel is not this config's (the
        free space is then seen anew)."""
        cfg = free_space_config(tsdf)
        if not np.isclose(voxel_m, cfg.voxel_m):
            return None
        keys, values = reblocked(keys, values, cfg.block_resolution)
        grid = grid_from_blocks(cfg, keys, values, FREE_ATTRIBUTES)
        return cls(tsdf, grid.to(o3c.Device(cfg.device)))

    def carve(
        self, depth_img: o3d.t.geometry.Image, frame: FusionFrame, T_world_camera: FloatArray
    ) -> None:
        """Integrate the blocks the frame's rays cross before its surface: depth_img is
        frame.depth_uint16 on the grid's device, seen from T_world_camera."""
        cfg = self.config
        keys = free_space_keys(frame.depth_m, frame.K, T_world_camera, cfg)
        if keys.size == 0:
            return
        coords = o3c.Tensor(unpack_keys(keys).astype(np.int32), o3c.int32, HOST).to(self._device)
        intrinsic = o3c.Tensor(open3d_projection(frame.K), o3c.float64, HOST)
        extrinsic = o3c.Tensor(np.linalg.inv(T_world_camera), o3c.float64, HOST)
        self._grid.integrate(
            coords,
            depth_img,
            intrinsic,
            extrinsic,
            frame.depth_units,
            cfg.depth_max_m,
            cfg.trunc_voxels,
        )
        self._dirty = np.union1d(self._dirty, keys)

    def take_dirty(self) -> Int64Array:
        """Packed keys (``occupancy.pack_keys``) of the blocks integrated since the last call
        (all of them at first)."""
        dirty, self._dirty = self._dirty, np.empty(0, np.int64)
        return dirty

    def all_keys(self) -> Int64Array:
        """Packed keys of every block, sorted."""
        return np.sort(pack_keys(active_keys(self._grid)))

    def read(
        self, select: Callable[[Int64Array], BoolArray] | None = None
    ) -> tuple[Int64Array, Float32Array]:
        """Keys (B, 3) and weights (B, z, y, x) of the blocks ``select`` keeps (None: all), as
        ``voxel_blocks.read_blocks``."""
        keys, _, weight = read_blocks(self._grid, select)
        return keys, weight

    def blocks(self) -> tuple[NDArray[np.int32], dict[str, Float32Array]]:
        """Keys (B, 3) and values per attribute (B, R, R, R, 1), copies, for a map file."""
        return read_all(self._grid, FREE_ATTRIBUTES)

    def memory_bytes(self) -> int:
        r = self.config.block_resolution
        return int(self._grid.hashmap().capacity()) * (r**3 * BYTES_PER_FREE_VOXEL + 3 * 4)
