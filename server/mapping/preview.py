"""Map preview for the phone: a few thousand new points at a time, each voxel sent once.

Built from the frames being fused rather than extracted from the TSDF, which costs the whole map
every time (over 100 ms for a room); a preview only needs to show where the map grows.
"""

from __future__ import annotations

import numpy as np

from server.geometry import Intrinsics, backproject


class MapPreview:
    """Tracks which voxels (edge ``voxel_m``) were already sent to the client."""

    def __init__(self, voxel_m: float = 0.04, stride: int = 4, max_depth_m: float = 4.0) -> None:
        self.voxel_m = voxel_m
        self.stride = stride
        self.max_depth_m = max_depth_m
        self._sent: set[int] = set()
        self._rng = np.random.default_rng(0)
        self.total = 0

    def new_points(
        self,
        colour: np.ndarray,
        depth: np.ndarray,
        K: Intrinsics,
        T_world_camera: np.ndarray,
        max_points: int,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Points (N, 3) float32 world metres and colours (N, 3) uint8 of voxels this frame shows
        for the first time, at most ``max_points`` (the rest can come with later frames)."""
        d = np.where(depth <= self.max_depth_m, depth, 0.0)
        points, uv = backproject(d, K, self.stride)
        if len(points) == 0:
            return np.empty((0, 3), np.float32), np.empty((0, 3), np.uint8)
        world = points @ T_world_camera[:3, :3].T + T_world_camera[:3, 3]
        ijk = np.floor(world / self.voxel_m).astype(np.int64) + (1 << 20)
        keys = (ijk[:, 0] << 42) | (ijk[:, 1] << 21) | ijk[:, 2]
        keys, first = np.unique(keys, return_index=True)
        fresh = ~np.fromiter(map(self._sent.__contains__, keys.tolist()), bool, len(keys))
        idx, new_keys = first[fresh], keys[fresh]
        if len(idx) > max_points:  # an even spread now, the rest with later frames
            pick = self._rng.choice(len(idx), max_points, replace=False)
            idx, new_keys = idx[pick], new_keys[pick]
        self._sent.update(new_keys.tolist())
        self.total += len(idx)
        rgb = colour[uv[idx, 1].astype(int), uv[idx, 0].astype(int)]
        return world[idx].astype(np.float32), rgb.astype(np.uint8)
