"""Record3D ``.r3d`` exports: an iPhone/iPad LiDAR recording in one zip file.

Layout (Record3D's export format):
    metadata       JSON: ``w``, ``h`` colour size; ``K`` its 3x3 intrinsic matrix, column-major
                   (pixels); ``dw``, ``dh`` depth size; ``fps``; ``poses`` one
                   ``[qx, qy, qz, qw, tx, ty, tz]`` per frame, ARKit's T_world_camera (camera x
                   right, y up, z backwards; metres); ``frameTimestamps`` (seconds, newer
                   versions); ``initPose`` and others, unused here
    rgbd/N.jpg     colour, frame N = 0, 1, ...
    rgbd/N.depth   LZFSE-compressed float32 depth, metres, dh x dw (NaN or 0 = no measurement)
    rgbd/N.conf    LZFSE-compressed uint8 ARKit confidence, 0 low, 1 medium, 2 high (optional)
The poses become ``device_poses`` in this project's camera axes (see server.datasets.arkit);
there is no ground truth. Depth is masked by confidence and resampled to the colour's size.
"""

from __future__ import annotations

import json
import logging
import math
import threading
import zipfile
from pathlib import Path

import cv2
import lzfse
import numpy as np

from server.datasets.arkit import DEFAULT_MIN_CONFIDENCE, camera_poses_from_arkit, lidar_depth
from server.datasets.base import RGBDDataset, RGBDFrame
from server.datasets.bounds import DEFAULT_LIMITS, DecodeLimits, jpeg_size, lzfse_size
from server.errors import DatasetError, DroneSimError
from server.evaluation.trajectory import Trajectory
from server.geometry import Intrinsics, pose_from_quaternion

logger = logging.getLogger(__name__)

R3D_SUFFIX = ".r3d"


def parse_metadata(data: dict) -> tuple[Intrinsics, tuple[int, int], np.ndarray, np.ndarray]:
    """Record3D metadata -> (colour intrinsics, depth (width, height), timestamps (N,) s,
    ARKit T_world_camera (N, 4, 4)). ValueError for values no recording has (sizes that are
    not positive whole numbers, a frame rate or pose that is not finite, timestamps that do
    not increase): such a file is refused, never stored."""
    width, height = _size(data["w"], "w"), _size(data["h"], "h")
    # Column-major: K = [fx, 0, 0, 0, fy, 0, cx, cy, 1].
    K = np.asarray(data["K"], dtype=np.float64).reshape(3, 3).T
    if not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError("K must hold finite numbers with positive focal lengths")
    intrinsics = Intrinsics(K[0, 0], K[1, 1], K[0, 2], K[1, 2], width, height)
    depth_size = (_size(data["dw"], "dw"), _size(data["dh"], "dh"))
    poses = np.asarray(data["poses"], dtype=np.float64).reshape(-1, 7)
    if not np.isfinite(poses).all():
        raise ValueError("poses must be finite numbers")
    T = np.array([pose_from_quaternion(p[4:], p[:4]) for p in poses]).reshape(-1, 4, 4)
    stamps = data.get("frameTimestamps")
    if stamps is None or len(stamps) != len(poses):
        fps = float(data["fps"])
        if not math.isfinite(fps) or fps <= 0:
            raise ValueError(f"fps must be a positive number, not {fps}")
        stamps = np.arange(len(poses)) / fps
    stamps = np.asarray(stamps, dtype=np.float64)
    if not np.isfinite(stamps).all() or (np.diff(stamps) <= 0).any():
        raise ValueError("frame timestamps must be finite and increasing")
    return intrinsics, depth_size, stamps, T


def _size(value: object, name: str, largest: int = 16384) -> int:
    """A pixel count from the metadata: a whole number in 1..largest, else ValueError."""
    number = float(value)  # type: ignore[arg-type]
    if not (math.isfinite(number) and number == int(number) and 1 <= number <= largest):
        raise ValueError(f"{name} must be a whole number of pixels in 1..{largest}, not {value}")
    return int(number)


class Record3DDataset(RGBDDataset):
    """A Record3D ``.r3d`` file.

    path: the .r3d file. intrinsics: overrides the metadata's K. min_confidence: ARKit confidence
    (0 low, 1 medium, 2 high) a depth pixel needs. limits: what the file may expand to, checked
    before each member is decoded (an upload's are the server's). ``device_poses``: the phone's
    odometry, T_world_camera in this project's camera axes and ARKit's world frame, one per
    frame.
    """

    depth_registered = True  # the phone registers its depth to its camera

    depth_scale = 1.0  # depth is stored as float metres

    def __init__(
        self,
        path: str | Path,
        intrinsics: Intrinsics | None = None,
        depth_scale: float | None = None,
        min_confidence: int = DEFAULT_MIN_CONFIDENCE,
        limits: DecodeLimits = DEFAULT_LIMITS,
    ):
        self.path = Path(path)
        self.name = self.path.stem
        if depth_scale is not None:
            raise DatasetError(
                f"{self.path}: Record3D depth is float metres; no depth scale applies"
            )
        if not self.path.is_file():
            raise DatasetError(f"Record3D file {self.path} does not exist")
        self.min_confidence = min_confidence
        self._lock = threading.Lock()
        self._zip: zipfile.ZipFile | None = None
        text = self._read("metadata", limits.max_metadata_bytes, "server.upload_max_metadata_mb")
        try:
            K, self._depth_size, stamps, arkit_poses = parse_metadata(json.loads(text))
        except (ValueError, TypeError, KeyError, DroneSimError) as exc:
            raise DatasetError(
                f"{self.path}: bad metadata (expected JSON with w, h, K, dw, dh, fps, poses): "
                f"{exc!r}"
            ) from exc
        limits.check_pixels(f"{self.path}: the colour image", K.width, K.height)
        limits.check_pixels(f"{self.path}: the depth image", *self._depth_size)
        limits.check_frames(f"{self.path}: the metadata", len(stamps))
        self.intrinsics = intrinsics or K
        self._timestamps = stamps
        names = set(self._archive().namelist())
        missing = [i for i in range(len(stamps)) if f"rgbd/{i}.depth" not in names]
        if missing:
            raise DatasetError(f"{self.path}: metadata lists frames without depth: {missing[:5]}")
        self._has_confidence = all(f"rgbd/{i}.conf" in names for i in range(len(stamps)))
        if not self._has_confidence:
            logger.warning("%s: no confidence maps, depth is not masked", self.name)
        self.device_poses = Trajectory(stamps.copy(), camera_poses_from_arkit(arkit_poses))
        self.ground_truth = None
        logger.info("%s: %d frames", self.name, len(self))

    def _archive(self) -> zipfile.ZipFile:
        if self._zip is None:
            try:
                self._zip = zipfile.ZipFile(self.path)
            except (OSError, zipfile.BadZipFile) as exc:
                raise DatasetError(f"{self.path}: not a readable .r3d (zip) file: {exc}") from exc
        return self._zip

    def _read(self, name: str, max_bytes: int, why: str) -> bytes:
        """Member ``name``, refused before it is inflated when it declares more than
        ``max_bytes`` (``why`` says what sets that bound); zipfile stops at the declared size,
        so the read is bounded."""
        with self._lock:
            archive = self._archive()
            try:
                declared = archive.getinfo(name).file_size
            except KeyError as exc:
                raise DatasetError(f"{self.path}: has no {name}") from exc
            if declared > max_bytes:
                raise DatasetError(
                    f"{self.path}: {name} unpacks to {declared / 1e6:.1f} MB, more than the "
                    f"{max_bytes / 1e6:.1f} MB allowed ({why})"
                )
            return archive.read(name)

    def _decompress(self, name: str, dtype: type, expected_items: int) -> np.ndarray:
        expected_bytes = expected_items * np.dtype(dtype).itemsize
        # LZFSE grows data it cannot compress by a few bytes per block, never by half.
        stream = self._read(name, expected_bytes + expected_bytes // 2 + 4096, "its depth size")
        declared = lzfse_size(stream) if stream[:3] == b"bvx" else -1
        if declared != expected_bytes:
            raise DatasetError(
                f"{self.path}: {name} "
                + (f"holds {declared} bytes" if declared >= 0 else "is not LZFSE-compressed")
                + f", expected {expected_bytes} "
                f"({self._depth_size[0]}x{self._depth_size[1]} {np.dtype(dtype).name})"
            )
        try:
            values: np.ndarray = np.frombuffer(lzfse.decompress(stream), dtype=dtype)
        except lzfse.error as exc:
            raise DatasetError(f"{self.path}: {name} is not LZFSE-compressed: {exc}") from exc
        if values.size != expected_items:  # the blocks lied about their sizes
            raise DatasetError(f"{self.path}: {name} holds {values.size} values")
        dw, dh = self._depth_size
        return values.reshape(dh, dw)

    def __len__(self) -> int:
        return len(self._timestamps)

    def __getitem__(self, index: int) -> RGBDFrame:
        index = self._frame_index(index)
        K = self.intrinsics
        # A JPEG larger than its raw pixels is no camera's: refused before it is inflated.
        data = self._read(f"rgbd/{index}.jpg", 3 * K.width * K.height + 2**20, "its colour size")
        try:
            size = jpeg_size(data)
        except DatasetError as exc:
            raise DatasetError(f"{self.path}: rgbd/{index}.jpg: {exc}") from exc
        if size != (K.width, K.height):  # checked before OpenCV allocates its pixels
            raise DatasetError(
                f"{self.path}: rgbd/{index}.jpg is {size[0]}x{size[1]} but the intrinsics say "
                f"{K.width}x{K.height}"
            )
        image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_COLOR)
        if image is None or image.shape[:2] != (K.height, K.width):
            raise DatasetError(f"{self.path}: rgbd/{index}.jpg is not a readable image")
        n = self._depth_size[0] * self._depth_size[1]
        depth = self._decompress(f"rgbd/{index}.depth", np.float32, n)
        confidence = (
            self._decompress(f"rgbd/{index}.conf", np.uint8, n) if self._has_confidence else None
        )
        return RGBDFrame(
            index=index,
            timestamp=float(self._timestamps[index]),
            colour=cv2.cvtColor(image, cv2.COLOR_BGR2RGB),
            depth=lidar_depth(depth, confidence, self.min_confidence, K.width, K.height),
        )

    @property
    def timestamps(self) -> np.ndarray:
        """Timestamps (N,) in seconds, one per frame."""
        return self._timestamps

    def __getstate__(self) -> dict:
        # An open zip file and a lock cannot travel to another process; the copy reopens.
        state = self.__dict__.copy()
        state["_zip"], state["_lock"] = None, None
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._lock = threading.Lock()
