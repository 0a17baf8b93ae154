"""Stray Scanner and Record3D loaders on recordings made here from synthetic_room0's first frames.

The fixtures (tests/support/iphone_recordings.py) follow each app's export layout with what an
iPhone would record: 256x192 LiDAR depth, a confidence map, and the camera's odometry in ARKit's
axes.
"""

from __future__ import annotations

import os
import pickle
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

from server.datasets import Record3DDataset, StrayDataset, open_dataset
from server.errors import DatasetError
from server.evaluation.metrics import associate_trajectories, ate
from server.evaluation.trajectory import read_tum
from server.geometry import invert
from server.pipeline import run_odometry
from server.registration.config import RegistrationConfig
from server.registration.preprocess import resample_depth
from tests.support.iphone_recordings import ROOM_K, room_recording, write_r3d, write_stray
from tests.support.paths import REPO, SHARED_DATA

DATA = SHARED_DATA
ROOM = DATA / "synthetic_room0"
pytestmark = [
    pytest.mark.slow,  # unit, not in the fast tier (tests/conftest.py)
    pytest.mark.skipif(not ROOM.is_dir(), reason=f"shared data not found at {ROOM}"),
]

FRAMES = 20


@pytest.fixture(scope="module")
def room():
    """The first frames of synthetic_room0 as a phone records them (iphone_recordings)."""
    return room_recording(ROOM, list(range(FRAMES)))


@pytest.fixture(scope="module")
def stray_dir(room, tmp_path_factory) -> Path:
    return write_stray(room, tmp_path_factory.mktemp("stray") / "room_scan")


@pytest.fixture(scope="module")
def r3d_file(room, tmp_path_factory) -> Path:
    return write_r3d(room, tmp_path_factory.mktemp("record3d") / "room_scan.r3d")


def expected_depth(room: dict, i: int, min_confidence: int) -> np.ndarray:
    """What frame i's depth should read as: masked at LiDAR size, then nearest-resampled."""
    lidar = np.nan_to_num(room["lidar"][i])
    masked = np.where(room["confidence"][i] >= min_confidence, lidar, 0.0).astype(np.float32)
    return resample_depth(masked, 640, 480)


def check_poses(ds, room: dict) -> None:
    """The device poses are the ground truth in the phone's world, in this project's axes."""
    poses = ds.device_poses.poses
    assert poses.shape == (FRAMES, 4, 4)
    np.testing.assert_allclose(poses, room["poses"], atol=1e-7)
    np.testing.assert_allclose(ds.device_poses.timestamps, ds.timestamps)
    assert ds.ground_truth is None
    # Camera-relative motion does not depend on the world frame: this pins the camera axes.
    rel = invert(poses[0]) @ poses[-1]
    rel_true = invert(room["poses"][0]) @ room["poses"][-1]
    np.testing.assert_allclose(rel, rel_true, atol=1e-7)
    # With this project's axes the camera looks along +z: the scene's depth is in front of it.
    assert np.median(ds[0].depth[ds[0].depth > 0]) > 0.3


@pytest.mark.parametrize("which", ["stray", "record3d"])
def test_open_dataset_recognises_iphone_recordings(which, stray_dir, r3d_file):
    path = stray_dir if which == "stray" else r3d_file
    ds = open_dataset(path)
    assert isinstance(ds, StrayDataset if which == "stray" else Record3DDataset)
    assert ds.name == "room_scan"
    assert len(ds) == FRAMES


def test_stray_intrinsics_colour_and_timestamps(stray_dir, room):
    ds = StrayDataset(stray_dir)
    assert ds.intrinsics == ROOM_K
    np.testing.assert_allclose(ds.timestamps, room["timestamps"], atol=1e-6)
    for i in (0, 7, 3, 19):  # out of order: going back reopens the video
        frame = ds[i]
        assert frame.index == i
        assert frame.colour.shape == (480, 640, 3) and frame.colour.dtype == np.uint8
        # mp4v is lossy; a wrong frame or swapped channels would be far off.
        error = np.abs(frame.colour.astype(float) - room["colour"][i].astype(float))
        assert error.mean() < 8.0, f"frame {i}: mean colour error {error.mean():.1f}"
        others = [j for j in (i - 5, i + 5) if 0 <= j < FRAMES]
        for j in others:
            assert error.mean() < np.abs(frame.colour.astype(float) - room["colour"][j]).mean()


@pytest.mark.parametrize("min_confidence", [0, 1, 2])
def test_stray_depth_in_metres_masked_by_confidence(stray_dir, room, min_confidence):
    ds = StrayDataset(stray_dir, min_confidence=min_confidence)
    for i in (0, 11):
        depth = ds[i].depth
        assert depth.dtype == np.float32 and depth.shape == (480, 640)
        want = expected_depth(room, i, min_confidence)
        np.testing.assert_allclose(depth, want, atol=0.0005 + 1e-6)  # millimetre PNG rounding
        conf = resample_depth(room["confidence"][i].astype(np.float32), 640, 480)
        assert np.all(depth[conf < min_confidence] == 0)
        assert np.count_nonzero(depth[conf >= min_confidence]) > 0.8 * np.sum(
            conf >= min_confidence
        )


def test_stray_device_poses_are_the_ground_truth_in_camera_axes(stray_dir, room):
    check_poses(StrayDataset(stray_dir), room)


def test_record3d_intrinsics_depth_confidence_and_poses(r3d_file, room):
    ds = Record3DDataset(r3d_file)
    assert ds.intrinsics == ROOM_K
    np.testing.assert_allclose(ds.timestamps, np.arange(FRAMES) / 30.0)  # no frameTimestamps
    for i in (4, 2):
        frame = ds[i]
        assert frame.colour.shape == (480, 640, 3) and frame.colour.dtype == np.uint8
        assert np.abs(frame.colour.astype(float) - room["colour"][i]).mean() < 4.0  # JPEG
        assert frame.depth.dtype == np.float32
        np.testing.assert_allclose(frame.depth, expected_depth(room, i, 1), atol=1e-7)
        assert np.all(np.isfinite(frame.depth))  # NaN holes read as 0
    strict = Record3DDataset(r3d_file, min_confidence=2)
    np.testing.assert_allclose(strict[4].depth, expected_depth(room, 4, 2), atol=1e-7)
    check_poses(ds, room)


@pytest.mark.parametrize("which", ["stray", "record3d"])
def test_iphone_datasets_survive_pickling(which, stray_dir, r3d_file):
    """A dataset may be handed to another process: the open video or zip is not carried."""
    ds = open_dataset(stray_dir if which == "stray" else r3d_file)
    first = ds[5]
    copy = pickle.loads(pickle.dumps(ds))
    np.testing.assert_array_equal(copy[5].colour, first.colour)
    np.testing.assert_array_equal(copy[5].depth, first.depth)


def test_broken_recordings_raise_dataset_errors(stray_dir, r3d_file, tmp_path):
    with pytest.raises(DatasetError, match="float metres"):
        Record3DDataset(r3d_file, depth_scale=1000.0)
    with zipfile.ZipFile(r3d_file) as src, zipfile.ZipFile(tmp_path / "cut.r3d", "w") as dst:
        for item in src.namelist():
            if item != "rgbd/3.depth":
                dst.writestr(item, src.read(item))
    with pytest.raises(DatasetError, match="without depth"):
        open_dataset(tmp_path / "cut.r3d")
    broken = tmp_path / "broken"
    broken.mkdir()
    for item in stray_dir.iterdir():
        (broken / item.name).symlink_to(item, target_is_directory=item.is_dir())
    (broken / "odometry.csv").unlink()
    (broken / "odometry.csv").write_text("time, x, y\n1, 2, 3\n")
    with pytest.raises(DatasetError, match="odometry.csv"):
        open_dataset(broken, "stray")


def test_track_runs_on_a_stray_recording(stray_dir):
    ds = open_dataset(stray_dir)
    run = run_odometry(ds, progress=False)
    states = [r.state.value for r in run.results]
    assert "lost" not in states, states
    gt, est = associate_trajectories(ds.device_poses, run.trajectory)
    assert len(gt) == FRAMES
    # The tracker starts at the identity (no ground truth): compare after a rigid alignment.
    # The path is ~0.5 m long; with lossy video and millimetre depth the error was ~1 mm.
    assert ate(gt, est)["rmse"] < 0.01


def test_track_command_reads_a_record3d_file(r3d_file, tmp_path):
    """``python -m server track FILE.r3d`` opens the zip by its suffix and tracks it."""
    out = tmp_path / "out"
    env = {k: v for k, v in os.environ.items() if not k.upper().startswith("DRONESIM_")}
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "server",
            "track",
            str(r3d_file),
            "--frames",
            "8",
            "--out",
            str(out),
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    trajectory = read_tum(out / "latest" / "trajectory.tum")
    np.testing.assert_allclose(trajectory.timestamps, np.arange(8) / 30.0, atol=1e-6)
    assert "room_scan" in proc.stdout


@pytest.mark.parametrize(
    "video_size",
    [(1920, 1440), (1280, 960)],
    ids=["full-resolution video", "video re-encoded smaller"],
)
def test_stray_frames_and_intrinsics_at_the_working_size(room, tmp_path, video_size):
    """The app writes camera_matrix.csv for the camera's 1920x1440 and its video may be that
    size (or re-encoded smaller) while the depth is 256x192: frames come at 640x480, with the
    matrix scaled to them from the size its principal point tells."""
    folder = write_stray(room, tmp_path / "big", video_size=video_size, matrix_size=(1920, 1440))
    ds = open_dataset(folder)
    assert ds.size == (640, 480)
    K = ds.intrinsics
    assert (K.width, K.height) == (640, 480)
    np.testing.assert_allclose([K.fx, K.fy, K.cx, K.cy], [525.0, 525.0, 319.5, 239.5], atol=1e-6)
    frame = ds[3]
    assert frame.colour.shape == (480, 640, 3) and frame.depth.shape == (480, 640)
    assert np.abs(frame.colour.astype(float) - room["colour"][3]).mean() < 8.0
    np.testing.assert_allclose(frame.depth, expected_depth(room, 3, 1), atol=0.0005 + 1e-6)
    # Geometry holds only with the right intrinsics: track without the prior.
    off = RegistrationConfig().with_overrides(prior={"enabled": False})
    run = run_odometry(ds, off, max_frames=12, progress=False)
    assert "lost" not in run.summary["states"]
    gt, est = associate_trajectories(ds.device_poses, run.trajectory)
    assert ate(gt, est)["rmse"] < 0.01


def test_stray_refuses_a_camera_matrix_or_depth_of_another_shape(room, tmp_path):
    folder = write_stray(room, tmp_path / "scan")
    (folder / "camera_matrix.csv").write_text("525,0,600\n0,525,100\n0,0,1\n")
    with pytest.raises(DatasetError, match="principal point"):
        open_dataset(folder)
    wide = write_stray(room, tmp_path / "wide", video_size=(640, 360))
    with pytest.raises(DatasetError, match="same field of view"):
        open_dataset(wide)
