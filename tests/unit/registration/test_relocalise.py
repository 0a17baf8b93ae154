"""Recovery after a loss: a frame flow cannot register is found again by place recognition among
every keyframe (in the same frame); when nothing registers for a few frames, a new map segment
starts, is tracked on its own (weak, not fused) and merges into the map when it sees it again."""

from __future__ import annotations

import numpy as np
import pytest

from server.datasets import open_dataset
from server.datasets.there_and_back import Reordered
from server.errors import ConfigError
from server.geometry import invert, rotation_angle_deg
from server.mapping.pointcloud import PointCloudMap
from server.pipeline import ground_truth_pose_at, run_odometry
from server.registration import Tracker, TrackingState
from server.registration.config import RegistrationConfig

pytestmark = pytest.mark.slow  # unit, not in the fast tier (tests/conftest.py)

FLOW_ONLY = RegistrationConfig().with_overrides(relocalise={"enabled": False})


def load(shared_data, name: str, indices) -> tuple:
    """The dataset, the frames with these indices and their ground-truth poses (by index)."""
    ds = open_dataset(shared_data / name)
    frames = {i: ds[i] for i in sorted(set(indices))}
    gt = {i: ground_truth_pose_at(ds, f.timestamp) for i, f in frames.items()}
    return ds, frames, gt


def run(ds, frames, gt, keep, config=None):
    tracker = Tracker(ds.intrinsics, config, T_world_first=gt[keep[0]])
    results = []
    for i in keep:
        results.append(tracker.track(frames[i].colour, frames[i].depth))
        tracker.update_keyframe()
    return results, tracker


def error(gt_a, gt_b, T_a, T_b) -> tuple[float, float]:
    """Error (metres, degrees) of the estimated motion a -> b against the true one."""
    E = invert(invert(gt_a) @ gt_b) @ (invert(T_a) @ T_b)
    return float(np.linalg.norm(E[:3, 3])), rotation_angle_deg(E)


def longest_lost_run(results) -> int:
    run = best = 0
    for r in results:
        run = run + 1 if r.state is TrackingState.LOST else 0
        best = max(best, run)
    return best


@pytest.fixture(scope="module")
def tum_gap(shared_data):
    """tum_fr1_xyz (real Kinect frames, motion-capture truth) with 15 frames missing (0.5 s):
    what a busy phone or a blurred sweep leaves."""
    keep = list(range(0, 60)) + list(range(75, 100))
    return (*load(shared_data, "tum_fr1_xyz", range(100)), keep)


def test_a_gap_in_the_frames_is_found_again_in_the_same_frame(tum_gap):
    ds, frames, gt, keep = tum_gap
    after = keep.index(75)
    flow, _ = run(ds, frames, gt, keep, FLOW_ONLY)
    assert flow[after].state is TrackingState.LOST, "flow alone bridged the gap: no test"

    results, tracker = run(ds, frames, gt, keep)
    assert all(r.state is not TrackingState.LOST for r in results)
    assert results[after].relocalised and not results[after - 1].relocalised
    assert results[after].segment == 0 and results[after].fusable
    # Across the gap the motion is as good as tracking's own over as many frames without one.
    dt, dr = error(gt[59], gt[75], results[after - 1].T_world_camera, results[after].T_world_camera)
    continuous, _ = run(ds, frames, gt, list(range(100)))
    own = np.median(
        [
            error(
                gt[a], gt[a + 16], continuous[a].T_world_camera, continuous[a + 16].T_world_camera
            )
            for a in range(100 - 16)
        ],
        axis=0,
    )
    assert dt < 2 * own[0] and dr < 2 * own[1] + 0.5, (dt, dr, own)
    assert results[after].timings_ms["relocalise"] > 0
    assert len(tracker.recovery.relocaliser) == tracker.keyframe_count


def test_a_view_of_an_old_keyframe_is_found_among_all_keyframes(shared_data):
    """Back at the start after a walk round the room: the keyframes that see it are no longer
    among the recent ones flow would try; the place database holds every keyframe."""
    keep = list(range(0, 120, 2)) + [4, 6, 8, 10]
    ds, frames, gt = load(shared_data, "synthetic_room0", keep)
    back = keep.index(120 - 2) + 1
    flow, _ = run(ds, frames, gt, keep, FLOW_ONLY)
    assert flow[back].state is TrackingState.LOST

    results, tracker = run(ds, frames, gt, keep)
    assert results[back].relocalised and results[back].state is not TrackingState.LOST
    assert all(r.state is not TrackingState.LOST for r in results)
    recent = {k.id for k in tracker.recent}
    assert results[back].keyframe_id not in recent or results[back].new_keyframe
    for j in range(back, len(keep)):
        E = invert(gt[keep[j]]) @ results[j].T_world_camera
        assert np.linalg.norm(E[:3, 3]) < 0.015 and rotation_angle_deg(E) < 1.0, keep[j]


def test_a_new_segment_is_tracked_on_its_own_and_merges_when_it_sees_the_map(shared_data):
    """A jump of 0.9 m and 63 degrees to a view no keyframe shares: after ``reinit_after`` lost
    frames a segment starts at the motion model's pose; its frames are weak and not fused; walking
    back, it meets the map, and its poses move into the map's frame."""
    keep = list(range(0, 40, 2)) + list(range(74, 150, 2)) + list(range(147, 0, -3))
    ds, frames, gt = load(shared_data, "synthetic_room0", keep)
    cfg = RegistrationConfig()
    results, tracker = run(ds, frames, gt, keep, cfg)
    jump = keep.index(74)
    assert longest_lost_run(results) <= cfg.relocalise.reinit_after
    assert results[jump].state is TrackingState.LOST
    started = next(j for j, r in enumerate(results) if r.segment != 0)
    assert started == jump + cfg.relocalise.reinit_after - 1
    assert results[started].new_keyframe and results[started].state is TrackingState.WEAK
    merged = next(j for j, r in enumerate(results) if r.merged is not None)
    segment = results[started].segment
    in_segment = results[started:merged]
    assert all(r.segment == segment and r.state is TrackingState.WEAK for r in in_segment)
    assert not any(r.fusable for r in in_segment)
    # The trajectory stays in one frame meanwhile: each segment pose follows the one before.
    for a, b in zip(in_segment[1:-1], in_segment[2:], strict=False):
        assert np.linalg.norm(b.T_world_camera[:3, 3] - a.T_world_camera[:3, 3]) < 0.1

    which, T_correction = results[merged].merged
    assert which == segment and results[merged].segment == 0
    assert np.linalg.norm(T_correction[:3, 3]) > 0.3  # the motion model was far off
    after = results[merged:]
    assert all(r.segment == 0 and r.state is not TrackingState.LOST for r in after)
    assert all(r.fusable for r in after if r.repeated is None)
    for j in range(merged, len(keep)):
        E = invert(gt[keep[j]]) @ results[j].T_world_camera
        assert np.linalg.norm(E[:3, 3]) < 0.02 and rotation_angle_deg(E) < 1.0, keep[j]
    # The segment's keyframes moved with it: every keyframe is in the map now.
    assert set(tracker.recovery.relocaliser.segment_of.values()) == {0}
    assert all(k.segment == 0 for k in tracker.recent)


def test_without_recovery_a_loss_can_last_forever(shared_data):
    """The same jump with recovery off: lost from the jump to the end (the reason for it)."""
    keep = list(range(0, 40, 2)) + list(range(74, 110, 2))
    ds, frames, gt = load(shared_data, "synthetic_room0", keep)
    results, _ = run(ds, frames, gt, keep, FLOW_ONLY)
    assert longest_lost_run(results) == len(keep) - keep.index(74)


@pytest.mark.parametrize(
    "values",
    [{"reinit_after": 0}, {"vote_keyframes": 0}, {"merge_every": 0}, {"orb_features": 5}],
)
def test_bad_recovery_settings_are_refused(values):
    with pytest.raises(ConfigError, match="relocalise"):
        RegistrationConfig().with_overrides(relocalise=values)


def test_track_fuses_a_merged_segments_keyframes_where_they_belong(shared_data):
    """Offline (``track``): a segment's keyframes stay out of the map until it merges, then go
    in at their corrected poses: their points lie on the same surfaces as those frames fused at
    their true poses."""
    keep = list(range(0, 40, 2)) + list(range(74, 150, 2)) + list(range(147, 0, -3))
    ds = open_dataset(shared_data / "synthetic_room0")
    cfg = RegistrationConfig().with_overrides(loops={"enabled": False})
    walk = Reordered(ds, keep)
    run = run_odometry(walk, cfg, progress=False, keep_room=False, overlap=False)
    in_segment = [
        (k, r) for k, r in enumerate(run.results) if r.recovery == "segment" and r.new_keyframe
    ]
    assert in_segment and any(r.merged is not None for r in run.results)
    for k, r in in_segment:
        fused = run.map._segments.get(r.keyframe_id)
        assert fused is not None and len(fused.points) > 1000, f"keyframe {r.keyframe_id}"
        truth = PointCloudMap()
        f = ds[keep[k]]
        T_true = ground_truth_pose_at(walk, walk[k].timestamp)  # the run starts at the truth
        truth.fuse(f.colour, f.depth, ds.intrinsics, T_true)
        off = np.asarray(fused.compute_point_cloud_distance(truth.cloud))
        assert np.median(off) < 0.02, (r.keyframe_id, np.median(off))
        # ... and not where the segment first put them (the motion model was far off).
        T_guess = r.T_world_camera
        assert np.linalg.norm(T_guess[:3, 3] - T_true[:3, 3]) > 0.3


def test_a_tracker_behind_looks_for_the_map_less_often_in_a_segment(shared_data):
    """A map segment looks itself up in the map every merge_every-th frame, and every
    merge_every_behind-th while the caller is behind (dropping frames): each look-up that fails
    costs several frames' tracking."""
    ds = open_dataset(shared_data / "synthetic_room0")
    walk = Reordered(ds, list(range(0, 40, 2)) + list(range(74, 150, 2)))  # a jump: a segment
    cfg = RegistrationConfig().with_overrides(loops={"enabled": False})
    r = cfg.relocalise
    assert r.merge_every_behind > r.merge_every
    gaps = {}
    for behind in (False, True):
        tracker = Tracker(ds.intrinsics, cfg)
        tracker.pace(behind)
        looked, segments = [], set()
        for k in range(len(walk)):
            frame = walk[k]
            result = tracker.track(frame.colour, frame.depth)
            tracker.update_keyframe()
            segments.add(result.segment)
            if "merge" in result.timings_ms:
                looked.append(k)
        assert len(segments - {0}) == 1 and len(looked) >= 3, (segments, looked)
        gaps[behind] = set(np.diff(looked).tolist())
    assert gaps == {False: {r.merge_every}, True: {r.merge_every_behind}}, gaps
