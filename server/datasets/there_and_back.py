"""A sequence played forward, then backward to its first frame: a camera that walks a path and
comes back along it, as a user who returns to where they started. Loop closure is measured on
it (tests/unit/registration/test_loops.py, benchmarks/loops.py): the way back sees the start again
after the tracker's recent keyframes have moved on."""

from __future__ import annotations

import numpy as np

from server.datasets.base import RGBDDataset, RGBDFrame
from server.evaluation.trajectory import Trajectory


class Reordered(RGBDDataset):
    """The frames of ``ds`` in the order ``order`` (indices; repeats allowed), with timestamps
    that go on at the sequence's frame rate and the ground truth (and device poses, when the
    sequence has them) to match: a walk the recording did not make, e.g. one that jumps."""

    def __init__(self, ds: RGBDDataset, order: list[int], name: str | None = None) -> None:
        if len(order) < 2 or not all(0 <= i < len(ds) for i in order):
            raise ValueError(f"a reordering needs 2 or more frames of 0..{len(ds) - 1}")
        self.ds = ds
        self.name, self.path = name or f"{ds.name}_reordered", ds.path
        self.intrinsics, self.depth_scale = ds.intrinsics, ds.depth_scale
        self.depth_registered = ds.depth_registered
        # The frame rate of the stretch the frames come from (ThereAndBack's first n frames).
        t = np.asarray(ds.timestamps[: max(order) + 1], dtype=np.float64)
        self.order = list(order)
        self._t = t[0] + float(np.median(np.diff(t))) * np.arange(len(self.order))
        self.ground_truth = self._replayed(ds.ground_truth, t)
        self.device_poses = self._replayed(ds.device_poses, t)

    def _replayed(self, trajectory: Trajectory | None, t: np.ndarray) -> Trajectory | None:
        """``trajectory``'s poses nearest each played frame, on the new timestamps."""
        if trajectory is None or len(trajectory.timestamps) == 0:
            return None
        nearest = [int(np.argmin(np.abs(trajectory.timestamps - t[i]))) for i in self.order]
        return Trajectory(self._t.copy(), trajectory.poses[nearest])

    def __len__(self) -> int:
        return len(self.order)

    def __getitem__(self, k: int) -> RGBDFrame:
        k = self._frame_index(k)
        f = self.ds[self.order[k]]
        return RGBDFrame(k, float(self._t[k]), f.colour, f.depth)

    @property
    def timestamps(self) -> np.ndarray:
        return self._t


class ThereAndBack(Reordered):
    """The first ``n`` frames of ``ds``, then the same frames backwards (the last not twice),
    with timestamps that go on at the sequence's frame rate and the ground truth (and device
    poses, when the sequence has them) to match."""

    def __init__(self, ds: RGBDDataset, n: int) -> None:
        if not 2 <= n <= len(ds):
            raise ValueError(f"there and back needs 2..{len(ds)} frames, got {n}")
        order = list(range(n)) + list(range(n - 2, -1, -1))
        super().__init__(ds, order, f"{ds.name}_there_and_back_{n}")
