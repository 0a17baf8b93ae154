"""The tracker's two phases: ``track`` returns the pose, ``update_keyframe`` builds keyframes."""

from __future__ import annotations

import numpy as np
import pytest

from server.datasets import open_dataset
from server.pipeline import ground_truth_pose_at, run_odometry
from server.registration import Tracker, TrackingState

pytestmark = pytest.mark.slow  # unit, not in the fast tier (tests/conftest.py)

FRAMES = 40


def two_phase_run(ds, n: int, update: bool):
    """Results and keyframe counts (after track, after update_keyframe) of the first n frames."""
    tracker = Tracker(ds.intrinsics, T_world_first=ground_truth_pose_at(ds, ds.timestamps[0]))
    results, counts = [], []
    for i in range(n):
        f = ds[i]
        r = tracker.track(f.colour, f.depth)
        after_track = tracker.keyframe_count
        made = tracker.update_keyframe() if update else False
        results.append(r)
        counts.append((after_track, tracker.keyframe_count, made))
    return tracker, results, counts


def test_track_returns_the_pose_before_the_keyframe_is_built(shared_data):
    ds = open_dataset(shared_data / "synthetic_room0")
    tracker, results, counts = two_phase_run(ds, FRAMES, update=True)
    assert all(r.state is not TrackingState.LOST for r in results)
    made_any = False
    for i, r in enumerate(results[1:], 1):
        before, after, made = counts[i]
        prev_after = counts[i - 1][1]
        # track() never builds a keyframe after the first frame; update_keyframe() does.
        assert before == prev_after, f"frame {i}: track() built a keyframe"
        assert after == before + made
        assert r.new_keyframe == made
        if made:
            made_any = True
            assert "keyframe" in r.timings_ms
            assert r.keyframe_id == after - 1  # the new keyframe is the one to track against
        assert not r.keyframe_due  # update_keyframe carried it out
    assert made_any, "the test needs frames that make keyframes"
    assert tracker.update_keyframe() is False  # nothing pending: a second call does nothing


def test_keyframe_due_is_reported_and_left_pending(shared_data):
    ds = open_dataset(shared_data / "synthetic_room0")
    tracker = Tracker(ds.intrinsics)
    for i in range(FRAMES):
        f = ds[i]
        r = tracker.track(f.colour, f.depth)
        if i > 0 and r.keyframe_due:
            count = tracker.keyframe_count
            assert not r.new_keyframe and "keyframe" not in r.timings_ms
            made = tracker.update_keyframe()
            assert tracker.keyframe_count == count + made
            assert r.new_keyframe == made and not r.keyframe_due
            return
    raise AssertionError("no keyframe change was due in the first frames")


def test_both_phases_give_the_pipelines_trajectory(shared_data):
    """Calling update_keyframe after each track, or leaving it to the next track, or the offline
    pipeline: one and the same trajectory and keyframes."""
    ds = open_dataset(shared_data / "synthetic_room0")
    run = run_odometry(ds, max_frames=FRAMES, progress=False)
    _, explicit, _ = two_phase_run(ds, FRAMES, update=True)
    lazy_tracker, lazy, _ = two_phase_run(ds, FRAMES, update=False)
    lazy_tracker.update_keyframe()  # the last frame's pending change
    poses = np.array([r.T_world_camera for r in explicit])
    np.testing.assert_array_equal(poses, run.trajectory.poses)
    np.testing.assert_array_equal(np.array([r.T_world_camera for r in lazy]), poses)
    # new_keyframe is known to the pipeline when it fuses, and the same for lazy callers in the end.
    assert [r.new_keyframe for r in run.results] == [r.new_keyframe for r in explicit]
    assert [r.new_keyframe for r in lazy] == [r.new_keyframe for r in explicit]
    assert run.summary["keyframes"] == lazy_tracker.keyframe_count
    assert sum(r.new_keyframe for r in explicit) >= 2
