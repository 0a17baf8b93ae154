"""Stray Scanner and Record3D loaders on recordings made here from synthetic_room0's first frames.

The fixtures follow each app's export layout with what an iPhone would record: 256x192 LiDAR
depth, a confidence map, and the camera's odometry in ARKit's axes (camera x right, y up, z back)
in a y-up world. The video is MPEG-4 Part 2 (mp4v), which OpenCV writes everywhere; the app writes
HEVC, which the loader decodes through the same FFmpeg path.
"""

from __future__ import annotations

import json
import os
import pickle
import subprocess
import sys
import zipfile
from pathlib import Path

import cv2
import lzfse
import numpy as np
import pytest

from server.datasets import Record3DDataset, StrayDataset, open_dataset
from server.errors import DatasetError
from server.evaluation.metrics import associate_trajectories, ate
from server.evaluation.trajectory import read_tum
from server.geometry import Intrinsics, invert, quaternion_from_pose
from server.pipeline import ground_truth_pose_at, run_odometry
from server.registration.preprocess import resample_depth

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data"
ROOM = DATA / "synthetic_room0"
pytestmark = pytest.mark.skipif(not ROOM.is_dir(), reason=f"shared data not found at {ROOM}")

FRAMES = 20
LIDAR_SIZE = (256, 192)  # width, height
ROOM_K = Intrinsics(525.0, 525.0, 319.5, 239.5, 640, 480)
# The phone's world is y up: the room's z-up world turned -90 degrees about x (y <- z, z <- -y).
ROOM_TO_PHONE_WORLD = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0], [0, -1.0, 0, 0], [0, 0, 0, 1.0]])
# ARKit's camera axes written out independently of the loader's constant.
CAMERA_TO_ARKIT = np.diag([1.0, -1.0, -1.0, 1.0])


def lidar_confidence(frame: int) -> np.ndarray:
    """A confidence map (192, 256): high, with a low strip at the left and a medium band at the
    bottom, moving with the frame so that each frame masks different pixels."""
    w, h = LIDAR_SIZE
    conf = np.full((h, w), 2, dtype=np.uint8)
    conf[:, frame : frame + 30] = 0
    conf[150:, :] = 1
    return conf


@pytest.fixture(scope="module")
def room():
    """The first frames of synthetic_room0: colour, LiDAR-sized depth (metres), confidence,
    T_world_camera in this project's axes and the phone's world, and ARKit-clock timestamps."""
    ds = open_dataset(ROOM)
    assert ds.intrinsics == ROOM_K
    frames = [ds[i] for i in range(FRAMES)]
    gt = np.array([ground_truth_pose_at(ds, f.timestamp) for f in frames])
    lidar = [resample_depth(f.depth, *LIDAR_SIZE) for f in frames]
    for d in lidar:
        d[5:9, 100:104] = np.nan  # ARKit leaves holes; Record3D stores them as NaN
    return {
        "colour": [f.colour for f in frames],
        "lidar": lidar,
        "confidence": [lidar_confidence(i) for i in range(FRAMES)],
        "poses": ROOM_TO_PHONE_WORLD @ gt,
        "timestamps": np.array([f.timestamp for f in frames]) - frames[0].timestamp + 5021.25,
    }


def arkit_rows(poses: np.ndarray):
    """(t, q_xyzw) of each pose after turning it to ARKit's camera axes."""
    for T in poses @ CAMERA_TO_ARKIT:
        yield T[:3, 3], quaternion_from_pose(T)


def write_stray(room: dict, folder: Path) -> Path:
    folder.mkdir()
    (folder / "depth").mkdir()
    (folder / "confidence").mkdir()
    video = cv2.VideoWriter(
        str(folder / "rgb.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 30.0, (640, 480)
    )
    assert video.isOpened(), "OpenCV cannot write mp4v here"
    for i, colour in enumerate(room["colour"]):
        video.write(cv2.cvtColor(colour, cv2.COLOR_RGB2BGR))
        mm = np.rint(np.nan_to_num(room["lidar"][i]) * 1000.0).astype(np.uint16)
        cv2.imwrite(str(folder / "depth" / f"{i:06d}.png"), mm)
        cv2.imwrite(str(folder / "confidence" / f"{i:06d}.png"), room["confidence"][i])
    video.release()
    K = ROOM_K.matrix  # the video has the room's size, so its matrix unscaled
    (folder / "camera_matrix.csv").write_text("\n".join(",".join(f"{v}" for v in r) for r in K))
    rows = ["timestamp, frame, x, y, z, qx, qy, qz, qw"]
    for i, (t, q) in enumerate(arkit_rows(room["poses"])):
        values = [*t, *q]
        rows.append(f"{room['timestamps'][i]:.6f}, {i}, " + ", ".join(f"{v:.12f}" for v in values))
    (folder / "odometry.csv").write_text("\n".join(rows) + "\n")
    return folder


def write_r3d(room: dict, path: Path) -> Path:
    K = ROOM_K.matrix
    metadata = {
        "w": 640,
        "h": 480,
        "K": K.T.reshape(-1).tolist(),  # column-major
        "dw": LIDAR_SIZE[0],
        "dh": LIDAR_SIZE[1],
        "fps": 30,
        "poses": [[*q, *t] for t, q in arkit_rows(room["poses"])],
        "initPose": [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0],
        "cameraType": 1,
    }
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("metadata", json.dumps(metadata))
        for i, colour in enumerate(room["colour"]):
            ok, jpg = cv2.imencode(".jpg", cv2.cvtColor(colour, cv2.COLOR_RGB2BGR))
            assert ok
            z.writestr(f"rgbd/{i}.jpg", jpg.tobytes())
            depth = room["lidar"][i].astype(np.float32)
            z.writestr(f"rgbd/{i}.depth", lzfse.compress(depth.tobytes()))
            z.writestr(f"rgbd/{i}.conf", lzfse.compress(room["confidence"][i].tobytes()))
    return path


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
    trajectory = read_tum(out / "trajectory.tum")
    np.testing.assert_allclose(trajectory.timestamps, np.arange(8) / 30.0, atol=1e-6)
    assert "room_scan" in proc.stdout
