"""The device's own pose as the tracker's prior: the initial guess across dropped frames, the
alignment of the device's world to the map, and no effect at all without a prior."""

from __future__ import annotations

import numpy as np
import pytest

from server.datasets import open_dataset
from server.errors import ConfigError
from server.evaluation.device_poses import (
    DeviceDrift,
    device_world,
    drifting_device_poses,
    exact_device_poses,
)
from server.evaluation.metrics import evaluate
from server.evaluation.trajectory import Trajectory
from server.geometry import exp_se3, invert, rotation_angle_deg
from server.pipeline import ground_truth_pose_at
from server.registration import Tracker, TrackingState
from server.registration.config import PriorConfig, RegistrationConfig
from server.registration.prior import DeviceAlignment, prior_motion

pytestmark = pytest.mark.slow  # unit, not in the fast tier (tests/conftest.py)


@pytest.fixture(scope="module")
def room(shared_data):
    """synthetic_room0 in memory: dataset, frames, stamps (s), ground truth (N, 4, 4)."""
    ds = open_dataset(shared_data / "synthetic_room0")
    frames = [ds[i] for i in range(len(ds))]
    stamps = np.array([f.timestamp for f in frames])
    gt = np.array([ground_truth_pose_at(ds, t) for t in stamps])
    return ds, frames, stamps, gt


def run(room, keep, priors=None, config=None, pass_none=False):
    """Track the kept frames (indices); returns the results and the tracker."""
    ds, frames, _, gt = room
    tracker = Tracker(ds.intrinsics, config, T_world_first=gt[keep[0]])
    results = []
    for i in keep:
        f = frames[i]
        if priors is not None:
            r = tracker.track(f.colour, f.depth, priors[i])
        elif pass_none:
            r = tracker.track(f.colour, f.depth, None)
        else:
            r = tracker.track(f.colour, f.depth)
        tracker.update_keyframe()
        results.append(r)
    return results, tracker


def ate(room, keep, results):
    ds, _, stamps, _ = room
    est = Trajectory(stamps[keep], np.array([r.T_world_camera for r in results]))
    return evaluate(ds.ground_truth, est)["ate_rmse_m"]


def lost(results):
    return sum(r.state is TrackingState.LOST for r in results)


def test_an_exact_prior_keeps_every_4th_to_8th_frame_tracked(room):
    """Only every 4th..8th frame arrives (gaps of 3..7 frames, up to 0.25 s at ~0.7 m/s): with
    the device's pose, in its own world frame, every frame is tracked and as accurate as without.
    (Constant velocity copes here too: the gaps are regular.)"""
    _, frames, _, gt = room
    priors = exact_device_poses(gt)
    for step in range(4, 9):
        keep = np.arange(0, len(frames), step)
        without, _ = run(room, keep)
        with_prior, _ = run(room, keep, priors)
        assert lost(with_prior) == 0, f"every {step}th frame: {lost(with_prior)} lost"
        assert all(r.prior_used for r in with_prior[1:])
        ate_with, ate_without = ate(room, keep, with_prior), ate(room, keep, without)
        assert ate_with < 0.005, f"every {step}th frame: ATE {ate_with * 100:.2f} cm"
        assert ate_with <= ate_without + 0.0005, f"every {step}th frame"


@pytest.mark.parametrize("burst", [10, 15, 20])
def test_an_exact_prior_bridges_bursts_of_dropped_frames(room, burst):
    """``burst`` frames in a row dropped after every 3 x burst received: constant velocity
    predicts one frame's motion for a gap of burst + 1 frames, and flow alone loses track (or
    worse: place recognition, off here, is what recovers it without a prior); the prior knows
    the motion and every frame is tracked."""
    _, frames, _, gt = room
    i = np.arange(len(frames))
    keep = i[i % (4 * burst) < 3 * burst]
    priors = exact_device_poses(gt)
    flow_only = RegistrationConfig().with_overrides(relocalise={"enabled": False})
    without, _ = run(room, keep, config=flow_only)
    with_prior, _ = run(room, keep, priors)
    ate_with, ate_without = ate(room, keep, with_prior), ate(room, keep, without)
    assert lost(with_prior) == 0
    assert ate_with < 0.005, f"ATE {ate_with * 100:.2f} cm"
    assert lost(without) > 0 or ate_without > ate_with


def test_poses_stay_in_the_map_when_the_prior_lives_in_another_world(room):
    _, frames, _, gt = room
    priors = exact_device_poses(gt, seed=3)
    keep = np.arange(0, 60, 2)
    results, tracker = run(room, keep, priors)
    # The device's world is far from the map's: a pose taken from it unmoved would be far off.
    assert np.linalg.norm(priors[keep[-1], :3, 3] - gt[keep[-1], :3, 3]) > 0.5
    for i, r in zip(keep, results, strict=True):
        E = invert(gt[i]) @ r.T_world_camera
        assert np.linalg.norm(E[:3, 3]) < 0.01 and rotation_angle_deg(E) < 0.5, f"frame {i}"
    # The alignment found is the inverse of the device world's pose.
    E = tracker.T_world_device @ device_world(3)
    assert np.linalg.norm(E[:3, 3]) < 0.01 and rotation_angle_deg(E) < 0.5


def test_a_drifting_prior_does_not_drift_the_trajectory(room):
    """A prior far worse than a phone's (10 % of path, 6 deg/s): only its frame-to-frame motion
    is used, so the trajectory stays as accurate as without it, while the prior drifts away."""
    _, frames, stamps, gt = room
    drift = DeviceDrift(translation_fraction=0.10, yaw_deg_per_s=6.0, seed=1)
    priors = drifting_device_poses(gt, stamps, drift)
    keep = np.arange(0, len(frames), 2)
    with_prior, tracker = run(room, keep, priors)
    without, _ = run(room, keep)
    assert lost(with_prior) == 0
    ate_with, ate_without = ate(room, keep, with_prior), ate(room, keep, without)
    assert ate_with < max(1.5 * ate_without, ate_without + 0.002)
    # The prior's own trajectory, aligned at the first frame, ends far off.
    T_world_device_first = gt[0] @ invert(priors[0])
    E = invert(gt[keep[-1]]) @ T_world_device_first @ priors[keep[-1]]
    assert rotation_angle_deg(E) > 10.0
    assert ate_with < 0.1 * float(np.linalg.norm(E[:3, 3]))
    # The alignment follows the drift: it fits the latest frames, not the first one.
    last = keep[-1]
    E_last = invert(gt[last]) @ tracker.T_world_device @ priors[last]
    assert rotation_angle_deg(E_last) < 0.3 * rotation_angle_deg(E)


def test_without_a_prior_results_are_bit_identical(room):
    keep = np.arange(0, 60)
    reference, _ = run(room, keep)
    explicit_none, _ = run(room, keep, pass_none=True)
    disabled = RegistrationConfig().with_overrides(prior={"enabled": False})
    ignored, tracker = run(room, keep, exact_device_poses(room[3]), config=disabled)
    for a, b, c in zip(reference, explicit_none, ignored, strict=True):
        np.testing.assert_array_equal(a.T_world_camera, b.T_world_camera)
        np.testing.assert_array_equal(a.T_world_camera, c.T_world_camera)
        assert a.state is b.state is c.state and a.inliers == b.inliers == c.inliers
        assert not (a.prior_used or b.prior_used or c.prior_used)
    assert tracker.T_world_device is None


def test_a_reset_of_the_device_world_is_survived_and_realigned(room):
    """The phone's own tracking restarts mid-way: its world jumps. The tracker ignores that one
    motion, keeps tracking, and aligns the new world."""
    _, frames, _, gt = room
    jump = exp_se3(np.array([0.0, 1.2, 0.0, 2.0, 0.0, -1.0]))
    priors = exact_device_poses(gt)
    priors[40:] = jump @ priors[40:]
    keep = np.arange(0, 80, 2)
    results, tracker = run(room, keep, priors)
    assert lost(results) == 0
    assert not results[list(keep).index(40)].prior_used  # the jump is not taken as motion
    assert all(r.prior_used for r in results[list(keep).index(42) :])
    E = tracker.T_world_device @ jump @ device_world(0)
    assert np.linalg.norm(E[:3, 3]) < 0.01 and rotation_angle_deg(E) < 0.5


def test_a_new_device_world_number_is_a_reset_even_for_a_small_jump(room):
    """A jump too small to tell from motion (8 cm, as ARCore's after relocalising) is taken as
    the camera's motion unless the frame says its prior is in a new device world
    (device_world): then that frame's prior is not used, the alignment starts again, and the
    frames after use the prior in the new world."""
    _, frames, _, gt = room
    jump = exp_se3(np.array([0.05, 0.0, 0.06, 0.0, 0.0, 0.0]))
    priors = exact_device_poses(gt)
    priors[40:] = jump @ priors[40:]
    keep = np.arange(0, 80, 2)
    at = list(keep).index(40)

    def track(worlds: bool):
        ds = room[0]
        tracker = Tracker(ds.intrinsics, T_world_first=gt[keep[0]])
        results = []
        for i in keep:
            world = int(worlds and i >= 40)
            results.append(tracker.track(frames[i].colour, frames[i].depth, priors[i], world))
            tracker.update_keyframe()
        return results, tracker

    told, tracker = track(worlds=True)
    assert not told[at].prior_used and all(r.prior_used for r in told[at + 1 :])
    E = tracker.T_world_device @ jump @ device_world(0)
    assert np.linalg.norm(E[:3, 3]) < 0.01 and rotation_angle_deg(E) < 0.5
    untold, _ = track(worlds=False)
    assert untold[at].prior_used  # taken as motion: only the number tells a reset here
    assert lost(told) == 0


def test_after_a_loss_the_prior_brings_tracking_back(room):
    """Blank frames while the camera moves on: with a prior the first real frame after them is
    found from the device's pose and tracked ok."""
    ds, frames, _, gt = room
    priors = exact_device_poses(gt)
    blank_colour = np.full_like(frames[0].colour, 128)
    blank_depth = np.full(frames[0].depth.shape, 1.5, np.float32)
    tracker = Tracker(ds.intrinsics, T_world_first=gt[0])
    for i in range(0, 20, 2):
        tracker.track(frames[i].colour, frames[i].depth, priors[i])
    for i in range(20, 36, 4):  # the camera moves on; the device still knows where it is
        assert tracker.track(blank_colour, blank_depth, priors[i]).state is TrackingState.LOST
    back = tracker.track(frames[36].colour, frames[36].depth, priors[36])
    assert back.state is TrackingState.OK and back.prior_used
    E = invert(gt[36]) @ back.T_world_camera
    assert np.linalg.norm(E[:3, 3]) < 0.01 and rotation_angle_deg(E) < 0.5


def test_alignment_ignores_a_badly_tracked_frame():
    alignment = DeviceAlignment(PriorConfig(alignment_frames=9))
    T_world_device = exp_se3(np.array([0.1, -0.4, 0.2, 1.0, 2.0, -0.5]))
    rng = np.random.default_rng(0)
    for k in range(9):
        T_device_camera = exp_se3(rng.normal(size=6))
        T_world_camera = T_world_device @ T_device_camera
        if k == 4:  # one frame's map pose 30 cm and 20 deg off
            T_world_camera = T_world_camera @ exp_se3(np.array([0.35, 0, 0, 0.3, 0, 0]))
        alignment.add(T_world_camera, T_device_camera)
    E = invert(T_world_device) @ alignment.T_world_device
    assert np.linalg.norm(E[:3, 3]) < 1e-9 and rotation_angle_deg(E) < 1e-6


def test_a_jump_is_not_motion_and_the_prior_config_is_checked():
    config = PriorConfig(max_motion_m=0.5, max_motion_deg=30.0)
    start = np.eye(4)
    assert prior_motion(start, exp_se3(np.array([0, 0.1, 0, 0.2, 0, 0])), config) is not None
    assert prior_motion(start, exp_se3(np.array([0, 0, 0, 0.6, 0, 0])), config) is None
    assert prior_motion(start, exp_se3(np.array([0, 0.6, 0, 0, 0, 0])), config) is None
    with pytest.raises(ConfigError, match="registration.prior"):
        RegistrationConfig().with_overrides(prior={"alignment_frames": 0})


def test_when_no_keyframe_sees_the_view_tracking_resumes_from_the_prior(room):
    """A long gap (the server too busy, the page hidden): the camera has moved on to a view no
    keyframe registers. With resume_after_loss (the default) the first frame after the gap
    starts a new keyframe at the device's pose (WEAK) and tracking goes on in the map; without
    it (and without place recognition's recovery), tracking stays lost for the rest of the
    sequence."""
    _, frames, stamps, gt = room
    priors = drifting_device_poses(gt, stamps, DeviceDrift(seed=2))
    keep = np.concatenate([np.arange(0, 40, 2), np.arange(74, len(frames), 2)])  # 0.9 m, 63 deg
    off = RegistrationConfig().with_overrides(
        prior={"resume_after_loss": False}, relocalise={"enabled": False}
    )
    stuck, _ = run(room, keep, priors, config=off)
    resumed, _ = run(room, keep, priors)
    first = list(keep).index(74)
    assert lost(stuck[first:]) >= 0.5 * len(keep[first:]), "the gap was bridged without resuming"
    assert lost(resumed) == 0
    assert resumed[first].state is TrackingState.WEAK and resumed[first].prior_used
    assert resumed[first].new_keyframe
    assert all(r.state is TrackingState.OK for r in resumed[first + 3 :])
    # Poses after the gap stay in the map: off by about the device's drift over the gap (3 % of
    # 0.9 m, plus its heading drift), which tracking then carries but does not grow.
    errors = []
    for i, r in zip(keep[first:], resumed[first:], strict=True):
        E = invert(gt[i]) @ r.T_world_camera
        errors.append(np.linalg.norm(E[:3, 3]))
        assert rotation_angle_deg(E) < 2.0, f"frame {i}"
    assert errors[0] < 0.04 and max(errors) < 0.08, np.round(errors, 3)


def test_a_repeated_frame_with_a_prior_moves_with_the_device(room):
    """A frame that repeats the previous depth is not tracked, but the device's own pose says
    how far the camera moved: the frame is placed by it, and tracking goes on after it."""
    ds, frames, _, gt = room
    priors = exact_device_poses(gt)
    tracker = Tracker(ds.intrinsics, T_world_first=gt[0])
    for i in range(5):
        last = tracker.track(frames[i].colour, frames[i].depth, priors[i])
        tracker.update_keyframe()
    held = tracker.track(frames[5].colour, frames[4].depth, priors[5])  # depth one frame late
    assert held.repeated == "depth" and held.prior_used
    # Placed by the device's (exact) motion since frame 4: off only by frame 4's own error.
    moved = invert(last.T_world_camera) @ held.T_world_camera
    np.testing.assert_allclose(moved, invert(gt[4]) @ gt[5], atol=1e-6)
    dt = np.linalg.norm((invert(gt[5]) @ held.T_world_camera)[:3, 3])
    assert dt < 0.003, f"{dt * 1e3:.1f} mm from the frame's true pose"
    after = tracker.track(frames[6].colour, frames[6].depth, priors[6])
    assert after.repeated is None and after.state is TrackingState.OK
    assert np.linalg.norm((invert(gt[6]) @ after.T_world_camera)[:3, 3]) < 0.002
