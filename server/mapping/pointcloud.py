"""A voxel-downsampled coloured point cloud fused from registered frames."""

from __future__ import annotations

import os

import numpy as np
import open3d as o3d

from server.geometry import Intrinsics, backproject


class PointCloudMap:
    """Accumulates frames' points in the world frame, keeping one point per voxel.

    voxel_m: voxel edge in metres. stride: back-project every stride-th pixel.
    max_depth_m: far points are noisy (error grows with z^2), so they are left out.
    """

    def __init__(self, voxel_m: float = 0.02, stride: int = 4, max_depth_m: float = 4.0) -> None:
        self.voxel_m = voxel_m
        self.stride = stride
        self.max_depth_m = max_depth_m
        self.cloud = o3d.geometry.PointCloud()
        self._pending = 0

    def fuse(
        self, colour: np.ndarray, depth: np.ndarray, K: Intrinsics, T_world_camera: np.ndarray
    ) -> None:
        """Add a frame: colour (H, W, 3) RGB uint8, depth (H, W) metres, pose T_world_camera."""
        d = np.where(depth <= self.max_depth_m, depth, 0.0)
        points, uv = backproject(d, K, self.stride)
        if len(points) == 0:
            return
        rgb = colour[uv[:, 1].astype(int), uv[:, 0].astype(int)].astype(np.float64) / 255.0
        world = points @ T_world_camera[:3, :3].T + T_world_camera[:3, 3]
        self.cloud.points.extend(o3d.utility.Vector3dVector(world))
        self.cloud.colors.extend(o3d.utility.Vector3dVector(rgb))
        self._pending += len(world)
        # Downsample in batches: once per frame would redo the whole map every frame (a million
        # points rather than 200 000: 7scenes_a's map is redone 4 times instead of 20).
        if self._pending > 1_000_000:
            self._downsample()

    def _downsample(self) -> None:
        # Only when points came: downsampling a downsampled cloud again moves its points (each
        # voxel's mean shifts the grid's share), so reading the map twice would differ.
        if self._pending:
            self.cloud = self.cloud.voxel_down_sample(self.voxel_m)
        self._pending = 0

    @property
    def points(self) -> np.ndarray:
        self._downsample()
        return np.asarray(self.cloud.points)

    @property
    def colours(self) -> np.ndarray:
        self._downsample()
        return np.asarray(self.cloud.colors)

    def write_ply(self, path: str | os.PathLike[str]) -> None:
        """Binary PLY with per-point colours."""
        self._downsample()
        # open3d's stubs ask for a PathLike; the binding takes a str as well.
        o3d.io.write_point_cloud(str(path), self.cloud, write_ascii=False)  # type: ignore[arg-type]
