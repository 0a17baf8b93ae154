"""The world point cloud of ``track``: one segment per keyframe, moved rigidly with a
correction exactly as if its frames had been fused at the corrected poses."""

from __future__ import annotations

import numpy as np

from server.geometry import Intrinsics
from server.geometry.se3 import exp_se3
from server.mapping.pointcloud import PointCloudMap

K = Intrinsics(fx=100.0, fy=100.0, cx=31.5, cy=23.5, width=64, height=48)


def _frame(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A sparse frame (every 16th pixel measured, 1-3 m): its points are 15+ cm apart, each
    alone in its 2 cm voxel, so downsampling keeps them exactly."""
    rng = np.random.default_rng(seed)
    depth = np.zeros((K.height, K.width), np.float32)
    depth[::16, ::16] = rng.uniform(1.0, 3.0, depth[::16, ::16].shape)
    colour = rng.integers(0, 256, (K.height, K.width, 3), dtype=np.uint8)
    return colour, depth


def _sorted(points: np.ndarray) -> np.ndarray:
    return points[np.lexsort(points.T[::-1])]


def test_a_moved_segment_is_where_its_frames_would_be_fused_at_the_corrected_pose():
    a, b = _frame(1), _frame(2)
    T_a = np.eye(4)
    T_b = exp_se3(np.array([0.3, 0.0, 0.1, 0.0, 0.2, 0.0]))
    correction = exp_se3(np.array([0.02, -0.01, 0.03, 0.01, -0.02, 0.015]))
    world = PointCloudMap(voxel_m=0.02, stride=1)
    world.fuse(*a, K, T_a, segment=0)
    world.fuse(*b, K, T_b, segment=1)
    before = world.points.copy()
    moved = world.moved({1: correction})

    expected = PointCloudMap(voxel_m=0.02, stride=1)
    expected.fuse(*a, K, T_a)
    expected.fuse(*b, K, correction @ T_b)
    assert len(moved.points) == len(expected.points) == 2 * 3 * 4
    np.testing.assert_allclose(_sorted(moved.points), _sorted(expected.points), atol=1e-9)
    np.testing.assert_allclose(
        moved.colours[np.lexsort(moved.points.T[::-1])],
        expected.colours[np.lexsort(expected.points.T[::-1])],
    )
    # The map it came from is unchanged, and an unnamed segment stays where it was.
    np.testing.assert_array_equal(world.points, before)
    assert np.allclose(_sorted(world.moved({}).points), _sorted(before))


def test_overlapping_segments_keep_one_point_per_voxel():
    colour, depth = _frame(3)
    world = PointCloudMap(voxel_m=0.02, stride=1)
    world.fuse(colour, depth, K, np.eye(4), segment=0)
    world.fuse(colour, depth, K, np.eye(4), segment=1)  # the same surface, seen twice
    assert len(world.points) == 3 * 4
