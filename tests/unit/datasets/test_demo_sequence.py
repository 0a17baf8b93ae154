"""The generated demo sequence: TUM layout, determinism, caching and exact ground truth."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import pytest

from server.datasets import demo
from server.datasets.demo import DemoSpec, demo_sequence_path, generate_demo_sequence
from server.geometry import invert, pose_from_quaternion, rotation_angle_deg

SMALL = DemoSpec(frames=12, width=320, height=240, fx=262.5, fy=262.5, cx=159.5, cy=119.5)
EXACT = dataclasses.replace(SMALL, noise=False)


def read_list(path: Path) -> list[list[str]]:
    """Non-comment lines of a TUM text file, split on whitespace."""
    lines = path.read_text().splitlines()
    return [line.split() for line in lines if line.strip() and not line.startswith("#")]


def read_depth(path: Path) -> np.ndarray:
    """Depth PNG -> metres, float32."""
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert raw is not None and raw.dtype == np.uint16
    return raw.astype(np.float32) / demo.DEPTH_SCALE


def read_poses(folder: Path) -> np.ndarray:
    """groundtruth.txt -> T_world_camera (N, 4, 4)."""
    rows = np.array(read_list(folder / "groundtruth.txt"), dtype=np.float64)
    return np.array([pose_from_quaternion(r[1:4], r[4:8]) for r in rows])


@pytest.fixture(scope="module")
def exact_sequence(tmp_path_factory) -> Path:
    return demo_sequence_path(EXACT, cache_dir=tmp_path_factory.mktemp("cache"), progress=False)


def test_layout_is_complete_and_parses(tmp_path):
    folder = demo_sequence_path(SMALL, cache_dir=tmp_path, progress=False)
    assert folder == tmp_path / f"demo-{SMALL.key()}"
    for name in ("rgb.txt", "depth.txt", "associations.txt", "groundtruth.txt", "README.txt"):
        assert (folder / name).is_file(), name
    intrinsics = json.loads((folder / "intrinsics.json").read_text())
    assert intrinsics == {
        "fx": 262.5,
        "fy": 262.5,
        "cx": 159.5,
        "cy": 119.5,
        "width": 320,
        "height": 240,
        "depth_scale": 5000.0,
    }
    rgb, depth = read_list(folder / "rgb.txt"), read_list(folder / "depth.txt")
    assoc, gt = read_list(folder / "associations.txt"), read_list(folder / "groundtruth.txt")
    assert len(rgb) == len(depth) == len(assoc) == len(gt) == SMALL.frames
    stamps = np.array([float(r[0]) for r in rgb])
    np.testing.assert_allclose(np.diff(stamps), 1 / SMALL.fps, atol=2e-6)
    for r, d, a, g in zip(rgb, depth, assoc, gt, strict=True):
        assert a == [r[0], r[1], d[0], d[1]] and g[0] == r[0] and len(g) == 8
        colour = cv2.imread(str(folder / r[1]))
        assert colour.shape == (240, 320, 3)
        assert read_depth(folder / d[1]).shape == (240, 320)
    quaternions = np.array([g[4:] for g in gt], dtype=np.float64)
    np.testing.assert_allclose(np.linalg.norm(quaternions, axis=1), 1.0, atol=1e-6)


def test_generation_is_deterministic(tmp_path):
    spec = dataclasses.replace(SMALL, frames=3)  # with noise: the noise is seeded too
    a = generate_demo_sequence(tmp_path / "a", spec, progress=False)
    b = generate_demo_sequence(tmp_path / "b", spec, progress=False)
    assert (a / "groundtruth.txt").read_text() == (b / "groundtruth.txt").read_text()
    for _, name in read_list(a / "depth.txt"):
        assert (a / name).read_bytes() == (b / name).read_bytes()
    other = generate_demo_sequence(
        tmp_path / "c", dataclasses.replace(spec, seed=8), progress=False
    )
    assert (a / "groundtruth.txt").read_text() != (other / "groundtruth.txt").read_text()


def test_cache_is_reused(tmp_path, monkeypatch):
    monkeypatch.setenv("DRONESIM_CACHE", str(tmp_path))
    spec = dataclasses.replace(SMALL, frames=2)
    folder = demo_sequence_path(spec, progress=False)
    assert folder.parent == tmp_path and (folder / ".complete").is_file()

    def fail(*args, **kwargs):
        raise AssertionError("regenerated a cached sequence")

    monkeypatch.setattr(demo, "generate_demo_sequence", fail)
    assert demo_sequence_path(spec, progress=False) == folder
    assert not list(tmp_path.glob(".*tmp*"))  # no temporary folder left behind


def test_cache_key_depends_on_every_field():
    keys = {DemoSpec().key()}
    for field, value in [
        ("frames", 10),
        ("width", 320),
        ("fps", 15.0),
        ("seed", 1),
        ("noise", False),
    ]:
        keys.add(dataclasses.replace(DemoSpec(), **{field: value}).key())
    assert len(keys) == 6


def test_ground_truth_is_geometrically_consistent(exact_sequence):
    depth_files = [name for _, name in read_list(exact_sequence / "depth.txt")]
    poses = read_poses(exact_sequence)
    K = EXACT.intrinsics
    z0, z3 = (
        read_depth(exact_sequence / depth_files[0]),
        read_depth(exact_sequence / depth_files[3]),
    )
    v, u = np.nonzero(z0 > 0)
    d = z0[v, u]
    points = np.stack([(u - K.cx) * d / K.fx, (v - K.cy) * d / K.fy, d, np.ones_like(d)], 1)
    in3 = (invert(poses[3]) @ poses[0] @ points.T).T  # frame 0 camera -> world -> frame 3 camera
    u3 = np.rint(in3[:, 0] / in3[:, 2] * K.fx + K.cx).astype(int)
    v3 = np.rint(in3[:, 1] / in3[:, 2] * K.fy + K.cy).astype(int)
    inside = (in3[:, 2] > 0.1) & (u3 >= 0) & (u3 < K.width) & (v3 >= 0) & (v3 < K.height)
    measured = z3[v3[inside], u3[inside]]
    diff = np.abs(measured - in3[inside, 2])
    visible = (measured > 0) & (diff < 0.05)  # not occluded in frame 3
    assert visible.sum() > 0.5 * len(d)
    assert np.median(diff[visible]) < 0.002


def test_exact_depth_has_few_holes_and_colour_has_texture(exact_sequence):
    fast = cv2.FastFeatureDetector_create()
    for rgb_name, depth_name in [
        (a[1], a[3]) for a in read_list(exact_sequence / "associations.txt")
    ]:
        assert (read_depth(exact_sequence / depth_name) > 0).mean() > 0.95
        grey = cv2.imread(str(exact_sequence / rgb_name), cv2.IMREAD_GRAYSCALE)
        assert len(fast.detect(grey)) > 200


def test_noise_makes_holes_at_grazing_angles_only(tmp_path):
    noisy = generate_demo_sequence(tmp_path / "noisy", dataclasses.replace(SMALL, frames=2), False)
    valid = [(read_depth(noisy / name) > 0).mean() for _, name in read_list(noisy / "depth.txt")]
    assert 0.8 < min(valid) and max(valid) < 1.0


def test_camera_path_is_hand_held_and_clear_of_surfaces():
    spec = DemoSpec()
    poses = demo.camera_poses(spec)
    R = poses[:, :3, :3]
    np.testing.assert_allclose(
        R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=1e-9
    )
    speed = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1) * spec.fps
    turn = np.array(
        [rotation_angle_deg(invert(a) @ b) for a, b in zip(poses[:-1], poses[1:], strict=True)]
    )
    turn *= spec.fps
    assert 0.3 < speed.mean() < 0.8 and speed.max() < 1.2  # m/s
    assert 12 < turn.mean() < 40 and turn.max() < 90  # deg/s
    scene, _ = demo.build_scene(spec)
    centres = o3d.core.Tensor(poses[:, :3, 3].astype(np.float32))
    assert scene.compute_distance(centres).numpy().min() > 0.5  # metres
