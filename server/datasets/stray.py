"""Stray Scanner exports: an iPhone/iPad LiDAR recording as the app writes it.

Layout (Stray Scanner's documented export format):
    rgb.mp4            the colour video (HEVC in the app; any codec OpenCV's FFmpeg decodes)
    depth/NNNNNN.png   uint16 millimetres, 256x192 on LiDAR devices, one per video frame
    confidence/NNNNNN.png  uint8 ARKit confidence, 0 low, 1 medium, 2 high (optional)
    camera_matrix.csv  the 3x3 intrinsic matrix, comma separated, for the video's resolution
    odometry.csv       ``timestamp, frame, x, y, z, qx, qy, qz, qw`` per frame: ARKit's
                       T_world_camera (seconds, metres, unit quaternion; camera x right, y up,
                       z backwards)
The odometry becomes ``device_poses`` in this project's camera axes (see server.datasets.arkit);
there is no ground truth. Depth is masked by confidence and resampled to the video's size.
"""

from __future__ import annotations

import csv
import logging
import threading
from pathlib import Path

import cv2
import numpy as np

from server.datasets.arkit import DEFAULT_MIN_CONFIDENCE, camera_poses_from_arkit, lidar_depth
from server.datasets.base import RGBDDataset, RGBDFrame
from server.errors import DatasetError, DroneSimError
from server.evaluation.trajectory import Trajectory
from server.geometry import Intrinsics, pose_from_quaternion

logger = logging.getLogger(__name__)

STRAY_DEPTH_SCALE = 1000.0  # depth PNG units (millimetres) per metre
ODOMETRY_COLUMNS = ("timestamp", "frame", "x", "y", "z", "qx", "qy", "qz", "qw")


def is_stray_folder(path: Path) -> bool:
    """Whether ``path`` looks like a Stray Scanner export (rgb.mp4, depth/, odometry.csv)."""
    return (
        (path / "rgb.mp4").is_file()
        and (path / "depth").is_dir()
        and (path / "odometry.csv").is_file()
    )


def read_camera_matrix(path: Path, width: int, height: int) -> Intrinsics:
    """Read ``camera_matrix.csv`` (3 rows of 3 comma-separated numbers, pixels) for an image of
    ``width`` x ``height`` pixels."""
    try:
        rows = [
            [float(v) for v in line.split(",")]
            for line in path.read_text().split("\n")
            if line.strip()
        ]
        K = np.array(rows)
        if K.shape != (3, 3):
            raise ValueError(f"expected 3 rows of 3 numbers, got shape {K.shape}")
        return Intrinsics(K[0, 0], K[1, 1], K[0, 2], K[1, 2], width, height)
    except (OSError, ValueError, DroneSimError) as exc:
        raise DatasetError(f"{path}: expected a 3x3 comma-separated camera matrix: {exc}") from exc


def read_odometry(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read ``odometry.csv`` -> (timestamps (N,) s, video frame numbers (N,), T_world_camera
    (N, 4, 4) in ARKit camera axes), sorted by frame number."""
    try:
        with path.open(newline="") as f:
            reader = csv.reader(f, skipinitialspace=True)
            header = [h.strip() for h in next(reader)]
            missing = [c for c in ODOMETRY_COLUMNS if c not in header]
            if missing:
                raise ValueError(f"header {header} lacks {missing}")
            col = {name: header.index(name) for name in ODOMETRY_COLUMNS}
            rows = [r for r in reader if r]
        stamps = np.array([float(r[col["timestamp"]]) for r in rows])
        frames = np.array([int(float(r[col["frame"]])) for r in rows])
        poses = np.array(
            [
                pose_from_quaternion(
                    np.array([float(r[col[k]]) for k in ("x", "y", "z")]),
                    np.array([float(r[col[k]]) for k in ("qx", "qy", "qz", "qw")]),
                )
                for r in rows
            ]
        ).reshape(-1, 4, 4)
    except (OSError, StopIteration, ValueError, IndexError) as exc:
        raise DatasetError(
            f"{path}: expected a csv with columns {', '.join(ODOMETRY_COLUMNS)}: {exc}"
        ) from exc
    if len(rows) == 0:
        raise DatasetError(f"{path}: no poses")
    order = np.argsort(frames, kind="stable")
    return stamps[order], frames[order], poses[order]


class VideoReader:
    """Frames of a video by index, decoded through OpenCV (FFmpeg). Reading in order decodes each
    frame once; going back reopens the file, as seeking in an inter-coded stream is inexact."""

    def __init__(self, path: Path):
        self.path = path
        self._lock = threading.Lock()
        self._capture: cv2.VideoCapture | None = None
        self._next = 0  # index of the frame the next read() returns
        capture = self._open()
        self.width = int(capture.get(cv2.CAP_PROP_FRAME_WIDTH))
        self.height = int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT))
        capture.release()

    def _open(self) -> cv2.VideoCapture:
        capture = cv2.VideoCapture(str(self.path))
        if not capture.isOpened():
            raise DatasetError(f"cannot open video {self.path} (missing, or a codec OpenCV lacks)")
        return capture

    def frame(self, index: int) -> np.ndarray:
        """Frame ``index`` as (H, W, 3) uint8 RGB."""
        with self._lock:
            if self._capture is None or index < self._next:
                if self._capture is not None:
                    self._capture.release()
                self._capture, self._next = self._open(), 0
            while self._next < index:
                if not self._capture.grab():
                    break
                self._next += 1
            ok, image = self._capture.read()
            if not ok or self._next != index:
                self._capture.release()
                self._capture = None
                raise DatasetError(f"{self.path}: cannot decode frame {index}")
            self._next += 1
        return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)

    def __getstate__(self) -> dict:
        # An open capture cannot travel to another process; the copy reopens on first read.
        return {"path": self.path, "width": self.width, "height": self.height}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._lock, self._capture, self._next = threading.Lock(), None, 0


class StrayDataset(RGBDDataset):
    """A Stray Scanner export folder.

    path: the folder. intrinsics: overrides camera_matrix.csv. depth_scale: depth PNG units per
    metre (1000). min_confidence: ARKit confidence (0 low, 1 medium, 2 high) a depth pixel needs.
    ``device_poses``: the phone's odometry, T_world_camera in this project's camera axes and
    ARKit's world frame, one per frame.
    """

    def __init__(
        self,
        path: str | Path,
        intrinsics: Intrinsics | None = None,
        depth_scale: float | None = None,
        min_confidence: int = DEFAULT_MIN_CONFIDENCE,
    ):
        self.path = Path(path)
        self.name = self.path.name
        if not self.path.is_dir():
            raise DatasetError(f"Stray Scanner folder {self.path} does not exist")
        if not is_stray_folder(self.path):
            raise DatasetError(f"{self.path}: expected rgb.mp4, depth/ and odometry.csv")
        self.depth_scale = depth_scale or STRAY_DEPTH_SCALE
        self.min_confidence = min_confidence
        self._video = VideoReader(self.path / "rgb.mp4")
        if intrinsics is not None:
            self.intrinsics = intrinsics
        else:
            self.intrinsics = read_camera_matrix(
                self.path / "camera_matrix.csv", self._video.width, self._video.height
            )
        if (self.intrinsics.width, self.intrinsics.height) != (
            self._video.width,
            self._video.height,
        ):
            raise DatasetError(
                f"{self.path}: rgb.mp4 is {self._video.width}x{self._video.height} but the "
                f"intrinsics say {self.intrinsics.width}x{self.intrinsics.height}"
            )

        stamps, frames, arkit_poses = read_odometry(self.path / "odometry.csv")
        self._frames = frames
        self._timestamps = stamps
        self._depth_files = [self.path / "depth" / f"{i:06d}.png" for i in frames]
        missing = [p.name for p in self._depth_files if not p.is_file()]
        if missing:
            raise DatasetError(
                f"{self.path}: odometry.csv lists frames without depth: {missing[:5]}"
            )
        confidence_dir = self.path / "confidence"
        self._confidence_files: list[Path] | None = None
        if confidence_dir.is_dir():
            self._confidence_files = [confidence_dir / f"{i:06d}.png" for i in frames]
        else:
            logger.warning("%s: no confidence/ folder, depth is not masked", self.name)
        self.device_poses = Trajectory(stamps.copy(), camera_poses_from_arkit(arkit_poses))
        self.ground_truth = None
        logger.info("%s: %d frames", self.name, len(self))

    def __len__(self) -> int:
        return len(self._timestamps)

    def __getitem__(self, index: int) -> RGBDFrame:
        index = self._frame_index(index)
        colour = self._video.frame(int(self._frames[index]))
        raw = cv2.imread(str(self._depth_files[index]), cv2.IMREAD_UNCHANGED)
        if raw is None or raw.dtype != np.uint16 or raw.ndim != 2:
            raise DatasetError(f"{self._depth_files[index]}: expected a 1-channel uint16 PNG")
        confidence = None
        if self._confidence_files is not None:
            confidence = cv2.imread(str(self._confidence_files[index]), cv2.IMREAD_UNCHANGED)
            if confidence is None:
                raise DatasetError(f"cannot read confidence map {self._confidence_files[index]}")
        try:
            depth = lidar_depth(
                raw.astype(np.float32) / np.float32(self.depth_scale),
                confidence,
                self.min_confidence,
                self.intrinsics.width,
                self.intrinsics.height,
            )
        except ValueError as exc:
            raise DatasetError(f"{self._depth_files[index]}: {exc}") from exc
        return RGBDFrame(
            index=index, timestamp=float(self._timestamps[index]), colour=colour, depth=depth
        )

    @property
    def timestamps(self) -> np.ndarray:
        """Timestamps (N,) in seconds (ARKit's clock), one per frame."""
        return self._timestamps
