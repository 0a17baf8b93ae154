"""TUM RGB-D sequences: ``rgb.txt``, ``depth.txt`` and an optional ``groundtruth.txt``.

Layout (https://cvg.cit.tum.de/data/datasets/rgbd-dataset/file_formats):
    rgb.txt, depth.txt   ``timestamp filename`` per line, '#' comments, paths relative to the folder
    groundtruth.txt      ``timestamp tx ty tz qx qy qz qw``, T_world_camera (metres)
    intrinsics.json      optional, ``fx fy cx cy width height depth_scale`` (this project's own)
Depth images are uint16 PNGs; depth in metres = value / depth_scale, 0 = no measurement.
"""

from __future__ import annotations

import json
import logging
import re
from pathlib import Path

import cv2
import numpy as np

from server.datasets.base import RGBDDataset, RGBDFrame
from server.errors import DatasetError, DroneSimError
from server.evaluation.trajectory import Trajectory, associate, read_tum
from server.geometry import Intrinsics
from server.textfile import data_lines

logger = logging.getLogger(__name__)

TUM_DEPTH_SCALE = 5000.0
# Factory calibration of the three TUM Kinects (fx, fy, cx, cy), 640x480.
TUM_DEFAULT_INTRINSICS = {
    "fr1": Intrinsics(517.3, 516.5, 318.6, 255.3, 640, 480),
    "fr2": Intrinsics(520.9, 521.0, 325.1, 249.7, 640, 480),
    "fr3": Intrinsics(535.4, 539.2, 320.1, 247.6, 640, 480),
}
INTRINSICS_FLAGS = "--fx --fy --cx --cy --width --height (and --depth-scale)"


def read_file_list(path: Path) -> tuple[np.ndarray, list[str]]:
    """Read a TUM ``timestamp filename`` list -> (timestamps (N,) s, filenames).

    Raises DatasetError naming the file (and line) when it is missing, malformed or empty.
    """
    stamps, names = [], []
    for line_no, line in data_lines(path, DatasetError):
        fields = line.replace(",", " ").split()
        try:
            if len(fields) < 2:
                raise ValueError("expected 'timestamp filename'")
            stamps.append(float(fields[0]))
        except ValueError as exc:
            raise DatasetError(
                f"{path}:{line_no}: bad row {line!r}, expected 'timestamp filename' ({exc})"
            ) from exc
        names.append(fields[1])
    if not names:
        raise DatasetError(f"{path}: lists no images")
    return np.array(stamps), names


def read_intrinsics_json(path: Path) -> tuple[Intrinsics, float | None]:
    """Read a flat ``{"fx", "fy", "cx", "cy", "width", "height", "depth_scale"?}`` json file.

    Returns (intrinsics in pixels, depth scale in units per metre or None when absent).
    """
    try:
        data = json.loads(path.read_text())
        K = Intrinsics(
            fx=float(data["fx"]),
            fy=float(data["fy"]),
            cx=float(data["cx"]),
            cy=float(data["cy"]),
            width=int(data["width"]),
            height=int(data["height"]),
        )
        scale = float(data["depth_scale"]) if "depth_scale" in data else None
    except (OSError, ValueError, TypeError, KeyError, DroneSimError) as exc:
        raise DatasetError(
            f"{path}: expected json with fx fy cx cy width height [depth_scale]: {exc!r}"
        ) from exc
    return K, scale


def read_colour(path: Path, K: Intrinsics) -> np.ndarray:
    """Read a colour image -> (H, W, 3) uint8 RGB; DatasetError if unreadable or not W x H."""
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise DatasetError(f"cannot read colour image {path} (missing or not an image)")
    _check_size(path, image, K)
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def read_depth(path: Path, depth_scale: float, K: Intrinsics) -> np.ndarray:
    """Read a uint16 depth image -> (H, W) float32 metres (value / depth_scale, 0 = invalid)."""
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise DatasetError(f"cannot read depth image {path} (missing or not an image)")
    if image.dtype != np.uint16 or image.ndim != 2:
        raise DatasetError(
            f"depth image {path} is {image.dtype} {image.shape}; expected 1-channel uint16"
        )
    _check_size(path, image, K)
    return (image.astype(np.float32) / np.float32(depth_scale)).astype(np.float32)


def _check_size(path: Path, image: np.ndarray, K: Intrinsics) -> None:
    h, w = image.shape[:2]
    if (w, h) != (K.width, K.height):
        raise DatasetError(f"{path} is {w}x{h} but the intrinsics say {K.width}x{K.height}")


def read_ground_truth(path: Path) -> Trajectory | None:
    """The TUM-format trajectory in ``path`` (T_world_camera, metres), or None if there is none."""
    if not path.is_file():
        return None
    try:
        return read_tum(path)
    except DroneSimError as exc:
        raise DatasetError(str(exc)) from exc


def tum_intrinsics(
    path: Path, intrinsics: Intrinsics | None, depth_scale: float | None
) -> tuple[Intrinsics, float]:
    """Pick (intrinsics, depth scale): explicit arguments, else intrinsics.json, else the TUM
    factory calibration named by the folder (fr1/fr2/fr3 or freiburg1/2/3)."""
    json_path = path / "intrinsics.json"
    json_K, json_scale = read_intrinsics_json(json_path) if json_path.is_file() else (None, None)
    if intrinsics is not None and json_K is not None and intrinsics != json_K:
        logger.warning("explicit intrinsics override %s", json_path)
    scale = depth_scale or json_scale or TUM_DEPTH_SCALE
    if not scale > 0:
        raise DatasetError(f"{path}: depth_scale must be positive, got {scale}")
    if intrinsics is not None:
        return intrinsics, scale
    if json_K is not None:
        return json_K, scale
    match = re.search(r"(?:fr|freiburg)([123])", path.name.lower())
    if match:
        key = f"fr{match.group(1)}"
        logger.info("%s: no intrinsics.json, using the TUM %s calibration", path.name, key)
        return TUM_DEFAULT_INTRINSICS[key], scale
    raise DatasetError(
        f"{path}: no intrinsics.json and the folder name names no TUM camera (fr1/fr2/fr3); "
        f"pass the intrinsics ({INTRINSICS_FLAGS})"
    )


class ImagePairDataset(RGBDDataset):
    """Frames stored as colour and depth image files paired one to one. Subclasses set
    ``_colour_files`` and ``_depth_files`` (lists of paths) and ``_timestamps`` ((N,) seconds)."""

    _colour_files: list[Path]
    _depth_files: list[Path]
    _timestamps: np.ndarray

    def __len__(self) -> int:
        return len(self._timestamps)

    def __getitem__(self, index: int) -> RGBDFrame:
        index = self._frame_index(index)
        return RGBDFrame(
            index=index,
            timestamp=float(self._timestamps[index]),
            colour=read_colour(self._colour_files[index], self.intrinsics),
            depth=read_depth(self._depth_files[index], self.depth_scale, self.intrinsics),
        )

    @property
    def timestamps(self) -> np.ndarray:
        """Timestamps (N,) in seconds, one per frame."""
        return self._timestamps


class TUMDataset(ImagePairDataset):
    """A TUM RGB-D sequence; colour and depth associated by nearest timestamp.

    path: the sequence folder. intrinsics, depth_scale (units per metre): override intrinsics.json
    and the TUM defaults. max_time_diff: largest accepted colour-depth time difference, seconds.
    """

    def __init__(
        self,
        path: str | Path,
        intrinsics: Intrinsics | None = None,
        depth_scale: float | None = None,
        max_time_diff: float = 0.02,
    ):
        self.path = Path(path)
        self.name = self.path.name
        if not self.path.is_dir():
            raise DatasetError(f"TUM sequence folder {self.path} does not exist")
        self.intrinsics, self.depth_scale = tum_intrinsics(self.path, intrinsics, depth_scale)

        rgb_stamps, rgb_names = read_file_list(self.path / "rgb.txt")
        depth_stamps, depth_names = read_file_list(self.path / "depth.txt")
        idx_rgb, idx_depth = associate(rgb_stamps, depth_stamps, max_time_diff)
        if len(idx_rgb) == 0:
            raise DatasetError(
                f"{self.path}: no rgb/depth timestamps match within "
                f"max_time_diff={max_time_diff} s "
                f"(rgb {rgb_stamps.min():.6f}-{rgb_stamps.max():.6f} s, "
                f"depth {depth_stamps.min():.6f}-{depth_stamps.max():.6f} s)"
            )
        self._timestamps = rgb_stamps[idx_rgb]
        self._colour_files = [self.path / rgb_names[i] for i in idx_rgb]
        self._depth_files = [self.path / depth_names[j] for j in idx_depth]
        logger.info(
            "%s: %d of %d rgb frames associated with depth", self.name, len(idx_rgb), len(rgb_names)
        )

        self.ground_truth = read_ground_truth(self.path / "groundtruth.txt")
