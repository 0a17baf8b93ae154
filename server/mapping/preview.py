"""Map preview for the phone: a few thousand new points at a time, each voxel sent once.

Built from the frames being fused rather than extracted from the TSDF, which costs the whole map
every time (over 100 ms for a room); a preview only needs to show where the map grows.
"""

from __future__ import annotations

import math

import numpy as np

from server.geometry import Intrinsics, backproject
from server.mapping.frame_input import intrinsics_at


class MapPreview:
    """Tracks which voxels (edge ``voxel_m``) were already sent to the client. A frame's depth is
    sampled at every n-th pixel each way, n the least that samples at most ``max_samples``
    pixels (every 4th of 640x480, each of ARCore's 160x72), whatever its size."""

    def __init__(
        self, voxel_m: float = 0.04, max_samples: int = 160 * 120, max_depth_m: float = 4.0
    ) -> None:
        self.voxel_m = voxel_m
        self.max_samples = max_samples
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
        for the first time, at most ``max_points`` (the rest can come with later frames). K is
        the camera's; depth and colour may each be at another size of the same aspect."""
        h, w = depth.shape
        d = np.where(depth <= self.max_depth_m, depth, 0.0)
        stride = max(1, math.ceil(math.sqrt(w * h / self.max_samples)))
        points, uv = backproject(d, intrinsics_at(K, w, h), stride)
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
        ch, cw = colour.shape[:2]
        u = np.minimum(((uv[idx, 0] + 0.5) * (cw / w)).astype(int), cw - 1)
        v = np.minimum(((uv[idx, 1] + 0.5) * (ch / h)).astype(int), ch - 1)
        rgb = colour[v, u]
        return world[idx].astype(np.float32), rgb.astype(np.uint8)
