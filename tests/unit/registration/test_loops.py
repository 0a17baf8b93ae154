"""Loop closure over keyframes: a sequence played forward then back returns to its start; the
loop is found, and the pose graph's correction leaves the trajectory no worse than odometry."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from server.datasets import open_dataset
from server.datasets.there_and_back import ThereAndBack
from server.mapping.config import MappingConfig
from server.mapping.pointcloud import PointCloudMap
from server.pipeline import run_odometry
from server.registration.config import RegistrationConfig

pytestmark = pytest.mark.slow  # unit, not in the fast tier (tests/conftest.py)


def test_a_loop_back_to_the_start_is_found_and_its_correction_does_not_add_error(shared_data):
    # 100 frames forward and back: 16 keyframes, of which the way back makes new ones once the
    # tracker's recent keyframes no longer reach the start (without loops it never returns).
    ds = ThereAndBack(open_dataset(shared_data / "synthetic_room0"), 100)
    cfg = RegistrationConfig().with_overrides(loops={"enabled": True, "min_separation": 8})
    run = run_odometry(ds, cfg, progress=False)
    loops = run.summary["loops"]
    assert loops["found"] >= 1
    assert [0, 15] in loops["edges"] or any(old <= 2 for old, _ in loops["edges"]), loops
    for old, new in loops["edges"]:
        assert new - old >= cfg.loops.min_separation
    before = loops["odometry_metrics"]["ate_rmse_m"]
    after = run.metrics["ate_rmse_m"]
    assert after <= before, (before, after)
    # The map followed: it lies where the same frames fused again at the corrected poses (which
    # differ from the odometry's) would put it, to within its voxels.
    odometry = np.array([r.T_world_camera for r in run.results])
    assert np.abs(run.trajectory.poses - odometry).max() > 1e-5
    voxel = MappingConfig().tsdf.voxel_m
    refused = _refused(ds, run, run.trajectory.poses)
    assert 0.9 < len(run.map.points) / len(refused) < 1.1
    assert np.percentile(_nearest(run.map.points, refused), 99) < voxel
    # ... and not where they were: the frames' points moved with their keyframes.
    moved = _nearest(_refused(ds, run, odometry), run.map.points)
    assert np.percentile(moved, 99) > np.percentile(_nearest(run.map.points, refused), 99)
    # The room's keyframes took the corrected poses (its map is re-fused from them when saved).
    assert run.room.map is None
    first = run.room.keyframes[0].T_world_keyframe
    assert np.allclose(first, ds.ground_truth.poses[0], atol=1e-6)  # the fixed reference


def _refused(ds, run, poses) -> np.ndarray:
    """The run's map made again from the frames it fused (keyframes and every fuse_every-th
    tracked frame) at ``poses``, in one segment."""
    every = MappingConfig().fuse_every
    world = PointCloudMap(voxel_m=MappingConfig().tsdf.voxel_m)
    for k, r in enumerate(run.results):
        if r.fusable and (r.new_keyframe or k % every == 0):
            frame = ds[k]
            world.fuse(frame.colour, frame.depth, ds.intrinsics, poses[k])
    return world.points


def _nearest(points: np.ndarray, cloud: np.ndarray) -> np.ndarray:
    """Each point's distance (metres) to the nearest point of ``cloud``."""
    tree = o3d.geometry.KDTreeFlann(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(cloud)))
    return np.array([np.sqrt(tree.search_knn_vector_3d(p, 1)[2][0]) for p in points])


def test_loop_closure_is_on_by_default_and_without_a_loop_changes_nothing(shared_data):
    """``track`` closes loops unless told not to; a run that finds none keeps the odometry's
    trajectory and map, as a run with loop closure off."""
    ds = open_dataset(shared_data / "synthetic_room0")
    on = run_odometry(ds, RegistrationConfig(), max_frames=10, progress=False)
    assert on.summary["loops"] == {"found": 0, "edges": []}
    off_cfg = RegistrationConfig().with_overrides(loops={"enabled": False})
    off = run_odometry(ds, off_cfg, max_frames=10, progress=False)
    assert "loops" not in off.summary
    np.testing.assert_array_equal(on.trajectory.poses, off.trajectory.poses)
    np.testing.assert_array_equal(on.map.points, off.map.points)
