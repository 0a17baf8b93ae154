"""A voxel-downsampled coloured point cloud fused from registered frames."""

from __future__ import annotations

import os
from collections.abc import Hashable, Mapping
from typing import Any

import numpy as np
import open3d as o3d

from server.geometry import Intrinsics, backproject
from server.geometry.arrays import FloatArray


class PointCloudMap:
    """Accumulates frames' points in the world frame, keeping one point per voxel.

    voxel_m: voxel edge in metres. stride: back-project every stride-th pixel.
    max_depth_m: far points are noisy (error grows with z^2), so they are left out.

    Frames are fused into segments (``fuse(..., segment=keyframe_id)``), each downsampled on its
    own, so that a pose-graph correction can move a keyframe's frames rigidly with it
    (:meth:`moved`) instead of decoding and fusing them all again. The map's points are the
    segments' together, one per voxel.
    """

    def __init__(self, voxel_m: float = 0.02, stride: int = 4, max_depth_m: float = 4.0) -> None:
        self.voxel_m = voxel_m
        self.stride = stride
        self.max_depth_m = max_depth_m
        self._segments: dict[Hashable, o3d.geometry.PointCloud] = {}
        self._pending: dict[Hashable, int] = {}  # points fused since a segment's downsampling
        self._last: Hashable | None = None
        self._merged: o3d.geometry.PointCloud | None = None

    def fuse(
        self,
        colour: np.ndarray,
        depth: np.ndarray,
        K: Intrinsics,
        T_world_camera: np.ndarray,
        segment: Hashable = None,
    ) -> None:
        """Add a frame: colour (H, W, 3) RGB uint8, depth (H, W) metres, pose T_world_camera,
        into ``segment`` (the keyframe it was tracked against; None: one segment for all)."""
        d = np.where(depth <= self.max_depth_m, depth, 0.0)
        points, uv = backproject(d, K, self.stride)
        if len(points) == 0:
            return
        rgb = colour[uv[:, 1].astype(int), uv[:, 0].astype(int)].astype(np.float64) / 255.0
        world = points @ T_world_camera[:3, :3].T + T_world_camera[:3, 3]
        if segment != self._last and self._last in self._segments:
            self._downsample(self._last)  # a keyframe's frames come together: its segment is done
        self._last = segment
        cloud = self._segments.setdefault(segment, o3d.geometry.PointCloud())
        cloud.points.extend(o3d.utility.Vector3dVector(world))
        cloud.colors.extend(o3d.utility.Vector3dVector(rgb))
        self._pending[segment] = self._pending.get(segment, 0) + len(world)
        self._merged = None
        # Downsample in batches: once per frame would redo the whole segment every frame.
        if self._pending[segment] > 1_000_000:
            self._downsample(segment)

    def moved(self, T_new_old: Mapping[Any, FloatArray]) -> PointCloudMap:
        """A new map with each segment moved rigidly by ``T_new_old[segment]`` (4x4, metres; a
        segment not named stays where it is). This map is unchanged."""
        out = PointCloudMap(self.voxel_m, self.stride, self.max_depth_m)
        for key in self._segments:
            self._downsample(key)
            cloud = o3d.geometry.PointCloud(self._segments[key])
            if key in T_new_old:
                cloud.transform(np.asarray(T_new_old[key], dtype=np.float64))
            out._segments[key] = cloud
            out._pending[key] = 0
        out._last = self._last
        return out

    def _downsample(self, segment: Hashable) -> None:
        # Only when points came: downsampling a downsampled cloud again moves its points (each
        # voxel's mean shifts the grid's share), so reading the map twice would differ.
        if self._pending.get(segment):
            self._segments[segment] = self._segments[segment].voxel_down_sample(self.voxel_m)
        self._pending[segment] = 0

    @property
    def cloud(self) -> o3d.geometry.PointCloud:
        """All segments' points, one per voxel (made again only after a fuse)."""
        if self._merged is None:
            merged = o3d.geometry.PointCloud()
            for key in self._segments:
                self._downsample(key)
                merged += self._segments[key]
            # One segment is downsampled already; several overlap and are merged per voxel.
            self._merged = (
                merged if len(self._segments) <= 1 else merged.voxel_down_sample(self.voxel_m)
            )
        return self._merged

    @property
    def points(self) -> np.ndarray:
        return np.asarray(self.cloud.points)

    @property
    def colours(self) -> np.ndarray:
        return np.asarray(self.cloud.colors)

    def write_ply(self, path: str | os.PathLike[str]) -> None:
        """Binary PLY with per-point colours."""
        # open3d's stubs ask for a PathLike; the binding takes a str as well.
        o3d.io.write_point_cloud(str(path), self.cloud, write_ascii=False)  # type: ignore[arg-type]
