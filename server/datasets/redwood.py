"""Redwood / Open3D RGB-D sequences: ``color/`` (or ``image/``) and ``depth/`` image folders.

Layout (as written by Open3D's reconstruction system and the Redwood datasets):
    color/ or image/      colour images, paired with depth by sorted file name
    depth/                uint16 PNGs in millimetres (depth scale 1000), 0 = no measurement
    camera_intrinsic.json or intrinsic.json   Open3D PinholeCameraIntrinsic, optional
    intrinsics.json       flat fx fy cx cy width height [depth_scale], optional
    groundtruth.txt       TUM-format T_world_camera, optional
There are no timestamps: frame i is stamped i / 30 s.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from server.datasets.tum import ImagePairDataset, read_ground_truth, read_intrinsics_json
from server.errors import DatasetError, DroneSimError
from server.geometry import Intrinsics

logger = logging.getLogger(__name__)

REDWOOD_DEPTH_SCALE = 1000.0
FRAME_RATE_HZ = 30.0
IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg"}
# Open3D's PinholeCameraIntrinsicParameters.PrimeSenseDefault.
PRIMESENSE_DEFAULT = Intrinsics(525.0, 525.0, 319.5, 239.5, 640, 480)
OPEN3D_INTRINSIC_FILES = ("camera_intrinsic.json", "intrinsic.json")


def read_open3d_intrinsic_json(path: Path) -> Intrinsics:
    """Read an Open3D PinholeCameraIntrinsic json: width, height and a column-major 3x3 matrix."""
    try:
        data = json.loads(path.read_text())
        m = [float(v) for v in data["intrinsic_matrix"]]
        if len(m) != 9:
            raise ValueError(f"intrinsic_matrix has {len(m)} numbers, expected 9")
        # Column-major: m = [fx, 0, 0, 0, fy, 0, cx, cy, 1].
        return Intrinsics(
            fx=m[0], fy=m[4], cx=m[6], cy=m[7], width=int(data["width"]), height=int(data["height"])
        )
    except (OSError, ValueError, TypeError, KeyError, DroneSimError) as exc:
        raise DatasetError(
            f"{path}: expected Open3D json {{'width', 'height', 'intrinsic_matrix': [9 numbers, "
            f"column-major]}}: {exc!r}"
        ) from exc


def redwood_intrinsics(path: Path, intrinsics: Intrinsics | None) -> tuple[Intrinsics, float]:
    """Pick (intrinsics, depth scale): explicit argument, else a json in the folder, else
    Open3D's PrimeSense default. Depth scale 1000 unless a flat intrinsics.json sets one."""
    scale, found = REDWOOD_DEPTH_SCALE, None
    for name in OPEN3D_INTRINSIC_FILES:
        if (path / name).is_file():
            found = read_open3d_intrinsic_json(path / name)
            break
    else:
        if (path / "intrinsics.json").is_file():
            found, json_scale = read_intrinsics_json(path / "intrinsics.json")
            scale = json_scale or scale
    if intrinsics is not None:
        if found is not None and found != intrinsics:
            logger.warning("%s: explicit intrinsics override the json in the folder", path)
        return intrinsics, scale
    if found is not None:
        return found, scale
    logger.info("%s: no intrinsics json, using Open3D's PrimeSense default", path.name)
    return PRIMESENSE_DEFAULT, scale


def _list_images(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)


class RedwoodDataset(ImagePairDataset):
    """A Redwood / Open3D RGB-D sequence; colour and depth paired by sorted file name.

    path: the sequence folder. intrinsics: overrides any json in the folder.
    """

    def __init__(self, path: str | Path, intrinsics: Intrinsics | None = None):
        self.path = Path(path)
        self.name = self.path.name
        if not self.path.is_dir():
            raise DatasetError(f"Redwood sequence folder {self.path} does not exist")
        colour_dir = next(
            (self.path / d for d in ("color", "image") if (self.path / d).is_dir()), None
        )
        depth_dir = self.path / "depth"
        if colour_dir is None or not depth_dir.is_dir():
            raise DatasetError(f"{self.path}: expected color/ (or image/) and depth/ folders")
        self._colour_files = _list_images(colour_dir)
        self._depth_files = _list_images(depth_dir)
        if len(self._colour_files) != len(self._depth_files):
            raise DatasetError(
                f"{self.path}: {len(self._colour_files)} colour images in {colour_dir.name}/ but "
                f"{len(self._depth_files)} depth images in depth/; they are paired by sorted order"
            )
        if not self._colour_files:
            raise DatasetError(f"{self.path}: no images in {colour_dir.name}/ and depth/")
        self.intrinsics, self.depth_scale = redwood_intrinsics(self.path, intrinsics)
        self._timestamps = np.arange(len(self._colour_files)) / FRAME_RATE_HZ

        self.ground_truth = read_ground_truth(self.path / "groundtruth.txt")
        logger.info("%s: %d frames", self.name, len(self))
