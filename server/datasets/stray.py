"""Stray Scanner exports: an iPhone/iPad LiDAR recording as the app writes it.

Layout (Stray Scanner's documented export format):
    rgb.mp4            the colour video (HEVC in the app; any codec OpenCV's FFmpeg decodes)
    depth/NNNNNN.png   uint16 millimetres, 256x192 on LiDAR devices, one per video frame
    confidence/NNNNNN.png  uint8 ARKit confidence, 0 low, 1 medium, 2 high (optional)
    camera_matrix.csv  the 3x3 intrinsic matrix, comma separated, for the camera's full
                       resolution (1920x1440; the video's size, unless it was re-encoded)
    odometry.csv       ``timestamp, frame, x, y, z, qx, qy, qz, qw`` per frame: ARKit's
                       T_world_camera (seconds, metres, unit quaternion; camera x right, y up,
                       z backwards)
The odometry becomes ``device_poses`` in this project's camera axes (see server.datasets.arkit);
there is no ground truth.

Frames come at a working size: the video's, divided by the smallest whole number that brings
its width to ``max_width`` (640) or below (1920x1440 -> 640x480: the tracker's and the wire's
usual size; the 256x192 depth holds no more detail than that). Colour is resized to it (area
filter), depth masked by confidence and resampled to it, and the intrinsics are scaled from the
size camera_matrix.csv was written for (told by its principal point, which sits near the
image's centre) to it.
"""

from __future__ import annotations

import csv
import logging
import threading
from fractions import Fraction
from pathlib import Path

import cv2
import numpy as np

from server.datasets.arkit import DEFAULT_MIN_CONFIDENCE, camera_poses_from_arkit, lidar_depth
from server.datasets.base import RGBDDataset, RGBDFrame
from server.datasets.bounds import DEFAULT_LIMITS, DecodeLimits, png_size
from server.errors import DatasetError
from server.evaluation.trajectory import Trajectory
from server.geometry import Intrinsics, pose_from_quaternion

logger = logging.getLogger(__name__)

STRAY_DEPTH_SCALE = 1000.0  # depth PNG units (millimetres) per metre
DEFAULT_MAX_WIDTH = 640  # widest frame the loader returns, px (see the module's docstring)
# Depth and video must show the same field of view: their width/height ratios may differ by this.
MAX_ASPECT_DIFFERENCE = 0.02
ODOMETRY_COLUMNS = ("timestamp", "frame", "x", "y", "z", "qx", "qy", "qz", "qw")


def is_stray_folder(path: Path) -> bool:
    """Whether ``path`` looks like a Stray Scanner export (rgb.mp4, depth/, odometry.csv)."""
    return (
        (path / "rgb.mp4").is_file()
        and (path / "depth").is_dir()
        and (path / "odometry.csv").is_file()
    )


def read_camera_matrix(path: Path) -> np.ndarray:
    """Read ``camera_matrix.csv``: 3 rows of 3 comma-separated numbers -> K (3, 3), pixels of
    the image size it was written for (which the file does not say; see ``matrix_size``)."""
    try:
        rows = [
            [float(v) for v in line.split(",")]
            for line in path.read_text().split("\n")
            if line.strip()
        ]
        K = np.array(rows)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise ValueError(f"expected 3 rows of 3 numbers, positive focal lengths; got {rows}")
        return K
    except (OSError, ValueError) as exc:
        raise DatasetError(f"{path}: expected a 3x3 comma-separated camera matrix: {exc}") from exc


def matrix_size(K: np.ndarray, width: int, height: int) -> tuple[int, int]:
    """The image size (px) a camera matrix was written for, given a video of ``width`` x
    ``height`` of the same camera: the video's size times the simple ratio (1, 3/2, 3, ...)
    that puts the principal point nearest the image's centre. The app writes the matrix for the
    camera's full resolution, and a recording may have been re-encoded smaller since.

    Raises DatasetError when the principal point fits no such size (not this video's camera)."""
    ratio_x = (K[0, 2] + 0.5) / (width / 2.0)
    ratio_y = (K[1, 2] + 0.5) / (height / 2.0)
    ratio = Fraction((ratio_x + ratio_y) / 2.0).limit_denominator(4)
    if ratio <= 0 or max(abs(ratio_x / ratio - 1), abs(ratio_y / ratio - 1)) > 0.1:
        raise DatasetError(
            f"camera_matrix.csv's principal point ({K[0, 2]:.1f}, {K[1, 2]:.1f}) fits no image "
            f"size of the video's shape ({width}x{height}): not this recording's camera"
        )
    return round(width * ratio), round(height * ratio)


def working_size(width: int, height: int, max_width: int) -> tuple[int, int]:
    """The video's size divided by the smallest whole number that brings the width to
    ``max_width`` or below (px)."""
    divisor = max(1, -(-width // max_width))
    return round(width / divisor), round(height / divisor)


def png_file_size(path: Path) -> tuple[int, int]:
    """(width, height) of a PNG file, px, from its header (no pixel is decoded)."""
    try:
        with path.open("rb") as f:
            return png_size(f.read(24))
    except (OSError, DatasetError) as exc:
        raise DatasetError(f"{path}: expected a PNG: {exc}") from exc


def read_odometry(
    path: Path, limits: DecodeLimits = DEFAULT_LIMITS
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read ``odometry.csv`` -> (timestamps (N,) s, video frame numbers (N,), T_world_camera
    (N, 4, 4) in ARKit camera axes), sorted by frame number; at most ``limits.max_frames``
    rows and ``limits.max_metadata_bytes`` bytes, checked before it is parsed."""
    if path.is_file():
        limits.check_text(str(path), path.stat().st_size)
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
    limits.check_frames(str(path), len(rows))
    if not (np.isfinite(stamps).all() and np.isfinite(poses).all()):
        raise DatasetError(f"{path}: odometry.csv holds timestamps or poses that are not finite")
    order = np.argsort(frames, kind="stable")
    return stamps[order], frames[order], poses[order]


class VideoReader:
    """Frames of a video by index, decoded through OpenCV (FFmpeg). Reading in order decodes each
    frame once; going back reopens the file, as seeking in an inter-coded stream is inexact."""

    def __init__(self, path: Path, limits: DecodeLimits = DEFAULT_LIMITS):
        self.path = path
        self._lock = threading.Lock()
        self._capture: cv2.VideoCapture | None = None
        self._next = 0  # index of the frame the next read() returns
        capture = self._open()
        self.width = int(capture.get(cv2.CAP_PROP_FRAME_WIDTH))
        self.height = int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT))
        capture.release()
        # The container's header says the frame size: refused before a frame is decoded.
        limits.check_pixels(f"{path}: its frames", self.width, self.height)

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
    max_width: widest frame returned, px (the video is scaled down by a whole number to fit).
    limits: what the export may expand to, checked before each file is decoded (an upload's
    are the server's). ``size``: (width, height) of the frames returned, px; ``intrinsics``
    are for it.
    ``device_poses``: the phone's odometry, T_world_camera in this project's camera axes and
    ARKit's world frame, one per frame.
    """

    depth_registered = True  # the phone registers its depth to its camera

    def __init__(
        self,
        path: str | Path,
        intrinsics: Intrinsics | None = None,
        depth_scale: float | None = None,
        min_confidence: int = DEFAULT_MIN_CONFIDENCE,
        max_width: int = DEFAULT_MAX_WIDTH,
        limits: DecodeLimits = DEFAULT_LIMITS,
    ):
        self.path = Path(path)
        self.name = self.path.name
        if not self.path.is_dir():
            raise DatasetError(f"Stray Scanner folder {self.path} does not exist")
        if not is_stray_folder(self.path):
            raise DatasetError(f"{self.path}: expected rgb.mp4, depth/ and odometry.csv")
        self.depth_scale = depth_scale or STRAY_DEPTH_SCALE
        self.min_confidence = min_confidence
        self._video = VideoReader(self.path / "rgb.mp4", limits)
        video = (self._video.width, self._video.height)
        self.size = working_size(*video, max_width)
        if intrinsics is not None:
            source = intrinsics  # at the size it says
        else:
            K = read_camera_matrix(self.path / "camera_matrix.csv")
            w, h = matrix_size(K, *video)
            source = Intrinsics(K[0, 0], K[1, 1], K[0, 2], K[1, 2], w, h)
        if abs(source.width / source.height / (video[0] / video[1]) - 1) > MAX_ASPECT_DIFFERENCE:
            raise DatasetError(
                f"{self.path}: rgb.mp4 is {video[0]}x{video[1]} but the intrinsics are for "
                f"{source.width}x{source.height}, another shape"
            )
        self.intrinsics = source.scaled(self.size[0] / source.width)
        if self.intrinsics.width != self.size[0] or self.intrinsics.height != self.size[1]:
            raise DatasetError(
                f"{self.path}: intrinsics for {source.width}x{source.height} do not scale to "
                f"frames of {self.size[0]}x{self.size[1]}"
            )
        if self.size != video or source.width != video[0]:
            logger.info(
                "%s: video %dx%d, camera matrix for %dx%d, frames and intrinsics at %dx%d",
                self.name,
                *video,
                source.width,
                source.height,
                *self.size,
            )

        stamps, frames, arkit_poses = read_odometry(self.path / "odometry.csv", limits)
        self._frames = frames
        self._timestamps = stamps
        self._depth_files = [self.path / "depth" / f"{i:06d}.png" for i in frames]
        missing = [p.name for p in self._depth_files if not p.is_file()]
        if missing:
            raise DatasetError(
                f"{self.path}: odometry.csv lists frames without depth: {missing[:5]}"
            )
        depth_size = self._depth_size = png_file_size(self._depth_files[0])
        limits.check_pixels(str(self._depth_files[0]), *depth_size)
        if abs(depth_size[0] / depth_size[1] / (video[0] / video[1]) - 1) > MAX_ASPECT_DIFFERENCE:
            raise DatasetError(
                f"{self.path}: depth is {depth_size[0]}x{depth_size[1]} and rgb.mp4 "
                f"{video[0]}x{video[1]}: not the same field of view"
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
        if (colour.shape[1], colour.shape[0]) != self.size:
            colour = cv2.resize(colour, self.size, interpolation=cv2.INTER_AREA)
        raw = self._read_png(self._depth_files[index])
        if raw is None or raw.dtype != np.uint16 or raw.ndim != 2:
            raise DatasetError(f"{self._depth_files[index]}: expected a 1-channel uint16 PNG")
        confidence = None
        if self._confidence_files is not None:
            confidence = self._read_png(self._confidence_files[index])
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

    def _read_png(self, path: Path) -> np.ndarray | None:
        """A depth or confidence PNG, decoded only when its header gives the first depth
        image's size (so a file that declares gigapixels allocates nothing); the file is read
        once, its header checked, then its bytes decoded."""
        try:
            data = path.read_bytes()
            size = png_size(data[:24])
        except (OSError, DatasetError) as exc:
            raise DatasetError(f"{path}: expected a PNG: {exc}") from exc
        if size != self._depth_size:
            raise DatasetError(
                f"{path}: is {size[0]}x{size[1]}, not the recording's depth size "
                f"{self._depth_size[0]}x{self._depth_size[1]}"
            )
        image: np.ndarray | None = cv2.imdecode(
            np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED
        )
        return image

    @property
    def timestamps(self) -> np.ndarray:
        """Timestamps (N,) in seconds (ARKit's clock), one per frame."""
        return self._timestamps
