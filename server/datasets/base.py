"""The one interface every RGB-D sequence loader implements."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from server.evaluation.trajectory import Trajectory
from server.geometry import Intrinsics


@dataclass
class RGBDFrame:
    """One registered RGB-D capture.

    colour: (H, W, 3) uint8, RGB channel order.
    depth:  (H, W) float32, metres along the optical axis, 0 where there is no measurement.
    timestamp: seconds.
    """

    index: int
    timestamp: float
    colour: np.ndarray
    depth: np.ndarray


class RGBDDataset:
    """A sequence of RGB-D frames with intrinsics and, when known, ground truth.

    Subclasses fill ``name``, ``path``, ``intrinsics``, ``depth_scale`` and ``ground_truth`` and
    implement ``__len__`` and ``__getitem__``. Recordings made by a phone also fill
    ``device_poses``: the phone's own odometry, T_world_camera (metres, this project's camera
    axes, the phone's world frame), one per frame with the frames' timestamps.
    """

    name: str
    path: Path
    intrinsics: Intrinsics
    depth_scale: float
    ground_truth: Trajectory | None = None
    device_poses: Trajectory | None = None
    # Depth registered to colour by the recording device itself (a phone's ARKit/ARCore depth);
    # False: it may not be (a raw RGB-D sensor), and colour is checked for it (ColourToDepth).
    depth_registered: bool = False

    def __len__(self) -> int:
        raise NotImplementedError

    def __getitem__(self, index: int) -> RGBDFrame:
        raise NotImplementedError

    def __iter__(self):
        for i in range(len(self)):
            yield self[i]

    def _frame_index(self, index: int) -> int:
        """``index`` as a position in 0..len-1 (negative counts from the end, as a list's);
        IndexError outside the sequence."""
        n = len(self)
        if not -n <= index < n:
            raise IndexError(f"frame {index} out of range for {n} frames")
        return index % n

    @property
    def timestamps(self) -> np.ndarray:
        raise NotImplementedError

    def device_pose(self, index: int, max_diff_s: float = 0.02) -> np.ndarray | None:
        """The phone's own T_world_camera (4x4, metres, its world frame) for frame ``index``,
        or None when the dataset has no device poses or none within ``max_diff_s`` seconds of
        the frame's timestamp. One pose per frame (the iPhone loaders) is matched by index."""
        poses = self.device_poses
        if poses is None or len(poses) == 0:
            return None
        index = self._frame_index(index)
        if len(poses) == len(self):
            return np.asarray(poses.poses[index], dtype=np.float64)
        t = float(self.timestamps[index])
        nearest = int(np.argmin(np.abs(poses.timestamps - t)))
        if abs(float(poses.timestamps[nearest]) - t) > max_diff_s:
            return None
        return np.asarray(poses.poses[nearest], dtype=np.float64)
