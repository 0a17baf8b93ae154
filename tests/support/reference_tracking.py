"""The offline reference the live-AR tests measure against: a sequence tracked at the page's
frame rate, full frames, no device pose."""

from __future__ import annotations

import numpy as np

from server.datasets.base import RGBDDataset
from server.evaluation.metrics import ate
from server.evaluation.trajectory import Trajectory
from server.registration.tracker import Tracker, TrackingState


def offline_ate_at(sequence: RGBDDataset, fps: float, recorded_fps: float = 30.0) -> float:
    """ATE (rmse, metres) of tracking ``sequence`` offline at ``fps`` (every n-th frame of its
    ``recorded_fps`` recording), full frames, no device pose, against its ground truth."""
    tracker = Tracker(sequence.intrinsics)
    stamps, poses = [], []
    for i in range(0, len(sequence), round(recorded_fps / fps)):
        frame = sequence[i]
        result = tracker.track(frame.colour, frame.depth)
        tracker.update_keyframe()
        if result.state is not TrackingState.LOST:
            stamps.append(frame.timestamp)
            poses.append(result.T_world_camera)
    gt = sequence.ground_truth
    assert gt is not None, f"{sequence.name} has no ground truth"
    idx = [int(np.argmin(np.abs(gt.timestamps - t))) for t in stamps]
    return ate(
        Trajectory(np.array(stamps), gt.poses[idx]), Trajectory(np.array(stamps), np.array(poses))
    )["rmse"]
