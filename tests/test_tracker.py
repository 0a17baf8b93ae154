"""The whole registration pipeline on synthetic and real frames."""

from __future__ import annotations

import numpy as np
import pytest

from server.datasets import open_dataset
from server.evaluation.metrics import evaluate
from server.evaluation.trajectory import Trajectory
from server.geometry import invert, rotation_angle_deg
from server.pipeline import ground_truth_pose_at
from server.registration import Tracker, TrackingState
from server.registration.config import RegistrationConfig


def relative_error(T_est, T_true):
    E = invert(T_true) @ T_est
    return float(np.linalg.norm(E[:3, 3])), rotation_angle_deg(E)


def gt_at(ds, i):
    return ground_truth_pose_at(ds, ds.timestamps[i])


@pytest.mark.parametrize("dense", [True, False])
def test_two_synthetic_frames_recover_the_known_transform(demo_clean, dense):
    ds = open_dataset(demo_clean)
    config = RegistrationConfig().with_overrides(solver={"dense": dense})
    tracker = Tracker(ds.intrinsics, config, T_world_first=gt_at(ds, 0))
    a, b = ds[0], ds[2]
    tracker.track(a.colour, a.depth)
    result = tracker.track(b.colour, b.depth)
    assert result.state is TrackingState.OK
    dt, dr = relative_error(result.T_world_camera, gt_at(ds, 2))
    assert dt < 0.001, f"translation error {dt * 1000:.2f} mm"
    assert dr < 0.05, f"rotation error {dr:.3f} deg"


def test_blank_wall_is_flagged_lost_holds_the_pose_and_recovers(demo_clean):
    ds = open_dataset(demo_clean)
    tracker = Tracker(ds.intrinsics, T_world_first=gt_at(ds, 0))
    for i in range(4):
        f = ds[i]
        good = tracker.track(f.colour, f.depth)
    assert good.state is TrackingState.OK
    keyframes_before = tracker.keyframe_count
    # The camera faces a blank, evenly lit wall 1.5 m away: nothing to track.
    wall_colour = np.full_like(ds[0].colour, 128)
    wall_depth = np.full(ds[0].depth.shape, 1.5, np.float32)
    for _ in range(3):
        lost = tracker.track(wall_colour, wall_depth)
        assert lost.state is TrackingState.LOST
        np.testing.assert_array_equal(lost.T_world_camera, good.T_world_camera)
    assert tracker.keyframe_count == keyframes_before  # no keyframe made from a lost view
    # The view returns: the tracker recovers against its keyframes with a correct pose.
    f = ds[5]
    back = tracker.track(f.colour, f.depth)
    assert back.state is TrackingState.OK
    dt, dr = relative_error(back.T_world_camera, gt_at(ds, 5))
    assert dt < 0.01 and dr < 0.5


def test_invalid_depth_values_are_ignored_not_propagated(demo_clean):
    ds = open_dataset(demo_clean)
    tracker = Tracker(ds.intrinsics, T_world_first=gt_at(ds, 0))
    for i in range(3):
        f = ds[i]
        depth = f.depth.copy()
        depth[::7, ::5] = np.nan
        depth[3::11, ::3] = np.inf
        depth[5::13, 1::4] = -1.0
        result = tracker.track(f.colour, depth)
    assert result.state is TrackingState.OK
    assert np.isfinite(result.T_world_camera).all()
    dt, _ = relative_error(result.T_world_camera, gt_at(ds, 2))
    assert dt < 0.005


def test_fast_hand_held_motion_keeps_tracking(demo_clean):
    """Every third frame of the demo path: about 1.5 m/s and up to ~90 deg/s at 30 Hz."""
    ds = open_dataset(demo_clean)
    frames = list(range(0, len(ds), 3))
    gt = np.array([gt_at(ds, i) for i in frames])
    step = np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1).max() * 30
    assert step > 1.0, f"the test path should be fast, peak {step:.2f} m/s"
    tracker = Tracker(ds.intrinsics, T_world_first=gt[0])
    est = []
    for i in frames:
        f = ds[i]
        r = tracker.track(f.colour, f.depth)
        assert r.state is not TrackingState.LOST
        est.append(r.T_world_camera)
    stamps = ds.timestamps[frames]
    metrics = evaluate(Trajectory(stamps, gt), Trajectory(stamps, np.array(est)))
    assert metrics["ate_rmse_m"] < 0.01


@pytest.mark.parametrize(
    "sequence, frames, max_ate_m", [("synthetic_room0", 60, 0.01), ("7scenes_a", 60, 0.02)]
)
def test_real_and_shared_sequences_track_without_loss(shared_data, sequence, frames, max_ate_m):
    ds = open_dataset(shared_data / sequence)
    tracker = Tracker(ds.intrinsics, T_world_first=gt_at(ds, 0))
    est = []
    for i in range(frames):
        f = ds[i]
        r = tracker.track(f.colour, f.depth)
        assert r.state is not TrackingState.LOST, f"frame {i} lost"
        est.append(r.T_world_camera)
    stamps = ds.timestamps[:frames]
    metrics = evaluate(ds.ground_truth, Trajectory(stamps, np.array(est)))
    assert metrics["ate_rmse_m"] < max_ate_m
