"""The whole registration pipeline on synthetic and real frames."""

from __future__ import annotations

import numpy as np
import pytest

from server.datasets import open_dataset
from server.evaluation.metrics import evaluate
from server.evaluation.trajectory import Trajectory
from server.geometry import invert, rotation_angle_deg
from server.pipeline import ground_truth_pose_at, run_odometry
from server.registration import Tracker, TrackingState
from server.registration.config import RegistrationConfig
from server.registration.frame_to_keyframe import refine_from_keyframe, track_keyframe
from server.registration.keyframes import refine_in_window, switch_keyframe


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


def test_colour_pixels_map_to_depth_pixels_by_focal_scale_and_offset():
    from server.geometry import Intrinsics
    from server.registration.preprocess import colour_to_depth_pixels, depth_to_colour_pixels

    K = Intrinsics(585.0, 585.0, 320.0, 240.0, 640, 480)
    uv = np.array([[320.0, 240.0], [20.0, 400.0]], np.float32)
    depth_cfg = RegistrationConfig().depth
    np.testing.assert_array_equal(colour_to_depth_pixels(uv, K, depth_cfg), uv)  # registered
    cfg = RegistrationConfig().with_overrides(
        depth={"colour_focal_scale": 0.9, "colour_offset_u_px": 4.0, "colour_offset_v_px": -2.0}
    )
    # A colour camera with 0.9x the depth focal length sees the border ray 1/0.9 further out.
    expected = [[324.0, 238.0], [320.0 - 300.0 / 0.9 + 4.0, 240.0 + 160.0 / 0.9 - 2.0]]
    np.testing.assert_allclose(colour_to_depth_pixels(uv, K, cfg.depth), expected, atol=1e-4)
    back = depth_to_colour_pixels(np.array(expected), K, cfg.depth)
    np.testing.assert_allclose(back, uv, atol=1e-4)


def unregistered_colour(colour: np.ndarray, K, scale: float) -> np.ndarray:
    """The colour image a camera with ``scale`` x the depth focal length (same centre) sees."""
    import cv2

    h, w = colour.shape[:2]
    u, v = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    # Colour pixel u_c shows what depth pixel c + (u_c - c) / scale shows.
    map_u = (K.cx + (u - K.cx) / scale).astype(np.float32)
    map_v = (K.cy + (v - K.cy) / scale).astype(np.float32)
    return cv2.remap(colour, map_u, map_v, cv2.INTER_LINEAR)


def test_colour_focal_scale_undoes_unregistered_colour(demo_clean):
    """A colour camera with a wider view than the depth camera (raw Kinect: 525 against 585 px)
    makes the tracker under-estimate rotation; resampling colour onto the depth image with the
    right focal scale (ColourToDepth, where frames come in) recovers it."""
    from server.registration.calibration import ColourToDepth

    ds = open_dataset(demo_clean)
    errors = {}
    for scale in (1.0, 0.9):
        config = RegistrationConfig().with_overrides(
            solver={"dense": False},
            depth={"colour_focal_scale": scale, "estimate_colour_registration": False},
        )
        to_depth = ColourToDepth(ds.intrinsics, config.depth)
        tracker = Tracker(ds.intrinsics, config, T_world_first=gt_at(ds, 0))
        for i in (0, 4):
            f = ds[i]
            colour = to_depth(unregistered_colour(f.colour, ds.intrinsics, 0.9), f.depth)
            result = tracker.track(colour, f.depth)
        assert result.state is not TrackingState.LOST
        errors[scale] = relative_error(result.T_world_camera, gt_at(ds, 4))
    true_rotation = rotation_angle_deg(invert(gt_at(ds, 0)) @ gt_at(ds, 4))
    assert true_rotation > 1.0  # the frames rotate enough for the bias to show
    assert errors[0.9][1] < 0.5 * errors[1.0][1], errors
    assert errors[0.9][1] < 0.1, errors


def test_windowed_keyframe_refinement_pulls_a_new_keyframe_towards_older_ones(demo_clean):
    """keyframes.window: a frame registered against a keyframe whose pose is 1 cm off is solved
    jointly with an older, correct keyframe; the joint pose lies between the two estimates,
    much nearer the truth than the current keyframe alone puts it."""
    from server.registration.preprocess import clean_depth, to_grey

    ds = open_dataset(demo_clean)
    config = RegistrationConfig().with_overrides(solver={"dense": False}, keyframes={"window": 2})
    tracker = Tracker(ds.intrinsics, config, T_world_first=gt_at(ds, 0))
    f0 = ds[0]
    tracker.track(f0.colour, f0.depth)  # keyframe A at the true pose
    frames = {i: (to_grey(ds[i].colour), clean_depth(ds[i].depth, config.depth)) for i in (2, 3)}
    off = np.eye(4)
    off[:3, 3] = [0.01, 0.0, 0.0]
    kf_b = tracker._new_keyframe(2, *frames[2], gt_at(ds, 2) @ off)  # keyframe B, 1 cm off
    reg = track_keyframe(kf_b, *frames[3], gt_at(ds, 3), ds.intrinsics, config)
    assert reg is not None
    T_via_b = kf_b.T_world_keyframe @ reg.solution.T
    error_b = relative_error(T_via_b, gt_at(ds, 3))[0]
    assert error_b > 0.008  # B's error passes to the frame
    T_joint = refine_in_window(tracker.recent, *frames[3], T_via_b, reg, ds.intrinsics, config)
    error_joint = relative_error(T_joint, gt_at(ds, 3))[0]
    assert error_joint < 0.7 * error_b, (error_joint, error_b)
    # With the window off, the frame keeps the pose from B alone.
    alone = RegistrationConfig().with_overrides(solver={"dense": False}, keyframes={"window": 0})
    T_alone = refine_in_window(tracker.recent, *frames[3], T_via_b, reg, ds.intrinsics, alone)
    np.testing.assert_array_equal(T_alone, T_via_b)


def test_a_tracker_behind_refines_new_keyframes_against_fewer_recent_ones(shared_data, monkeypatch):
    """keyframes.window_when_behind: while its caller is behind (``pace``), a new keyframe is
    refined against at most that many recent keyframes (each costs a registration), and
    against ``window`` again once it keeps up."""
    import server.registration.tracker as tracker_module

    windows: list[int | None] = []

    def refine(*args, **kwargs):
        windows.append(args[7] if len(args) > 7 else kwargs.get("window"))
        return refine_in_window(*args, **kwargs)

    monkeypatch.setattr(tracker_module, "refine_in_window", refine)
    ds = open_dataset(shared_data / "synthetic_room0")
    config = RegistrationConfig()
    assert config.keyframes.window > config.keyframes.window_when_behind >= 1
    tracker = Tracker(ds.intrinsics, config)
    seen = {}
    for behind, frames in ((False, range(0, 40)), (True, range(40, 80)), (False, range(80, 120))):
        tracker.pace(behind)
        windows.clear()
        for i in frames:
            tracker.track(ds[i].colour, ds[i].depth)
            tracker.update_keyframe()
        seen[behind] = seen.get(behind, set()) | set(windows)
        assert windows, f"no keyframe made in frames {frames}"
    assert seen == {False: {config.keyframes.window}, True: {config.keyframes.window_when_behind}}


def test_keyframe_realignment_pulls_wandered_tracks_back_onto_the_keyframe_corner(demo_clean):
    """flow.keyframe_refine_levels: a chained track that wandered 1.4 px off is re-aligned
    straight against the keyframe image; one moved beyond keyframe_refine_max_px is dropped."""

    ds = open_dataset(demo_clean)
    config = RegistrationConfig().with_overrides(
        flow={"keyframe_refine_levels": 1, "keyframe_refine_max_px": 2.0}
    )
    tracker = Tracker(ds.intrinsics, config, T_world_first=gt_at(ds, 0))
    f0 = ds[0]
    tracker.track(f0.colour, f0.depth)
    kf = tracker.keyframe
    assert kf is not None
    ids = np.arange(len(kf.uv))
    wandered = kf.uv + np.float32(1.0) * np.where(ids % 2 == 0, 1, -1)[:, None].astype(np.float32)
    kept, uv = refine_from_keyframe(kf, kf.grey, ids, wandered, config.flow)
    assert len(kept) > 0.8 * len(ids)
    assert np.median(np.linalg.norm(uv - kf.uv[kept], axis=1)) < 0.1
    far = kf.uv + np.float32(3.0)  # the true corner lies 4.2 px away: beyond the limit
    kept_far, _ = refine_from_keyframe(kf, kf.grey, ids, far, config.flow)
    assert len(kept_far) < 0.2 * len(ids)


@pytest.mark.parametrize("order, expected_frame", [("nearest", 1), ("oldest", 0)])
def test_keyframe_switch_order(demo_clean, order, expected_frame):
    """keyframes.switch_order: among earlier keyframes that see the view, "nearest" goes back to
    the one nearest the pose, "oldest" to the oldest (least drift along the chain)."""
    from server.registration.preprocess import clean_depth, to_grey

    ds = open_dataset(demo_clean)
    config = RegistrationConfig().with_overrides(
        solver={"dense": False}, keyframes={"switch_order": order}
    )
    tracker = Tracker(ds.intrinsics, config)
    images = {i: (to_grey(ds[i].colour), clean_depth(ds[i].depth, config.depth)) for i in (0, 1, 3)}
    for i in (0, 1, 3):
        tracker._new_keyframe(i, *images[i], gt_at(ds, i))  # the last one is current
    current, K = tracker.keyframe, ds.intrinsics
    switched = switch_keyframe(tracker.recent, [], current, 0, *images[1], gt_at(ds, 1), K, config)
    assert switched is not None
    assert switched[0].frame_index == expected_frame


def test_colour_registration_is_estimated_on_unregistered_images_only(demo_clean):
    """depth.estimate_colour_registration: a colour image with 0.9x the depth camera's focal
    length is found as such; registered images keep the identity."""
    import time

    from server.registration.calibration import ColourToDepth, estimate_colour_registration
    from server.registration.preprocess import to_grey

    ds = open_dataset(demo_clean)
    f = ds[0]
    assert estimate_colour_registration(to_grey(f.colour), f.depth, ds.intrinsics) is None
    t = time.perf_counter()
    grey = to_grey(unregistered_colour(f.colour, ds.intrinsics, 0.9))
    found = estimate_colour_registration(grey, f.depth, ds.intrinsics)
    assert time.perf_counter() - t < 5.0
    assert found is not None
    assert abs(found.scale - 0.9) <= 0.015
    assert abs(found.offset_u_px) <= 2 and abs(found.offset_v_px) <= 2
    # Where frames come in, the first frame's estimate resamples colour onto depth: the result
    # is (inside the borders, up to interpolation) the registered image.
    config = RegistrationConfig().with_overrides(depth={"estimate_colour_registration": True})
    to_depth = ColourToDepth(ds.intrinsics, config.depth)
    unregistered = unregistered_colour(f.colour, ds.intrinsics, 0.9)
    registered = to_depth(unregistered, f.depth)
    assert to_depth.mapping is not None and to_depth.mapping.scale == found.scale
    inner = (slice(60, -60), slice(80, -80))

    def off(img) -> float:
        return float(np.abs(img[inner].astype(float) - f.colour[inner].astype(float)).mean())

    assert off(registered) < 0.25 * off(unregistered), (off(registered), off(unregistered))
    # Registered streams pass through untouched.
    plain = ColourToDepth(ds.intrinsics, config.depth)
    assert plain(f.colour, f.depth) is f.colour and plain.mapping is None


def test_a_frame_that_repeats_its_colour_or_depth_is_held_at_the_last_pose(demo_clean):
    """Colour of one moment with depth of another (a depth sensor slower than the camera, a
    dropped frame filled with a repeat) is not tracked: the frame keeps the previous pose and
    state, and the next frame is tracked over the gap as usual."""
    ds = open_dataset(demo_clean)
    tracker = Tracker(ds.intrinsics, T_world_first=gt_at(ds, 0))
    for i in range(4):
        last = tracker.track(ds[i].colour, ds[i].depth)
        tracker.update_keyframe()
    keyframes = tracker.keyframe_count
    held = [
        tracker.track(ds[4].colour, ds[3].depth),  # new colour, the same depth
        tracker.track(ds[4].colour, ds[5].depth),  # the same colour, new depth
        tracker.track(ds[4].colour, ds[5].depth),  # both the same
    ]
    assert [r.repeated for r in held] == ["depth", "colour", "both"]
    for r in held:
        np.testing.assert_array_equal(r.T_world_camera, last.T_world_camera)
        assert r.state is last.state and not r.new_keyframe and not r.keyframe_due
        tracker.update_keyframe()
    assert tracker.keyframe_count == keyframes
    # Three frames later the camera has moved on: tracked from the prediction over the gap.
    after = tracker.track(ds[7].colour, ds[7].depth)
    assert after.repeated is None and after.state is TrackingState.OK
    dt, dr = relative_error(after.T_world_camera, gt_at(ds, 7))
    assert dt < 0.002 and dr < 0.1


def test_holding_repeated_frames_can_be_turned_off(demo_clean):
    ds = open_dataset(demo_clean)
    config = RegistrationConfig().with_overrides(state={"hold_repeated_frames": False})
    tracker = Tracker(ds.intrinsics, config, T_world_first=gt_at(ds, 0))
    first = tracker.track(ds[0].colour, ds[0].depth)
    tracker.update_keyframe()
    tracked = tracker.track(ds[2].colour, ds[0].depth)  # new colour, the first frame's depth
    assert tracked.repeated is None
    assert not np.array_equal(tracked.T_world_camera, first.T_world_camera)


def test_out_of_step_frames_of_7scenes_are_held_by_track(shared_data):
    """7scenes_a frames 215-235: frame 222 repeats its depth (colour new), 228 and 234 repeat
    both images. ``track`` holds them at the pose before and counts them."""
    ds = open_dataset(shared_data / "7scenes_a")
    run = run_odometry(ds, max_frames=21, start=215, progress=False, keep_room=False)
    assert run.summary["repeated"] == {"depth": 1, "both": 2}
    poses = run.trajectory.poses
    for k in (222 - 215, 228 - 215, 234 - 215):
        np.testing.assert_array_equal(poses[k], poses[k - 1])
    assert all(r.state is not TrackingState.LOST for r in run.results)
