"""A dataset written in the form the phone page replays (``ReplaySequence.fromServer``): one
colour JPEG and one 16-bit depth PNG per frame, and an index of them.

The index holds the camera (``intrinsics`` [fx, fy, cx, cy] px, ``colour_size`` and
``depth_size`` [width, height] px), ``depth_scale`` (PNG units per metre), ``fps``, ``gravity``
(in the first camera's frame, this project's axes, when the device poses tell it) and per frame
``{timestamp (s), colour, depth (file names), T_device_camera}``: the phone's own pose (16
floats, row-major, metres, this project's camera axes) when the recording has one.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from server.datasets.base import RGBDDataset
from server.errors import DatasetError
from server.geometry import Intrinsics

EXPORT_DEPTH_SCALE = 1000.0  # depth PNG units per metre: millimetres, as a phone's depth
MAX_DEPTH_M = 65.535  # the largest depth a uint16 millimetre PNG holds
JPEG_QUALITY = 90
# ARKit's world is y up: gravity points along -y (server/datasets/arkit.py).
ARKIT_GRAVITY = np.array([0.0, -1.0, 0.0])


def gravity_in_first_camera(dataset: RGBDDataset) -> list[float] | None:
    """Gravity (unit vector) in the first frame's camera axes, from the phone's y-up world; None
    without device poses."""
    pose = dataset.device_pose(0)
    if pose is None:
        return None
    return [float(v) for v in pose[:3, :3].T @ ARKIT_GRAVITY]


def export_replay(
    dataset: RGBDDataset,
    folder: Path,
    max_frames: int | None = None,
    on_frame: Callable[[int, int], None] | None = None,
) -> dict:
    """Write ``dataset`` (its first ``max_frames`` frames) into ``folder`` as ``rgb/NNNNNN.jpg``
    and ``depth/NNNNNN.png`` and return the index (file names relative to ``folder``).
    ``on_frame(done, total)`` follows the progress. Raises DatasetError when a frame cannot be
    read or written."""
    n = len(dataset) if max_frames is None else min(max_frames, len(dataset))
    if n < 1:
        raise DatasetError(f"{dataset.name}: no frames")
    (folder / "rgb").mkdir(parents=True, exist_ok=True)
    (folder / "depth").mkdir(exist_ok=True)
    K = dataset.intrinsics
    frames = []
    for i in range(n):
        frame = dataset[i]
        colour_name, depth_name = f"rgb/{i:06d}.jpg", f"depth/{i:06d}.png"
        bgr = cv2.cvtColor(frame.colour, cv2.COLOR_RGB2BGR)
        mm = np.rint(np.clip(frame.depth, 0.0, MAX_DEPTH_M) * EXPORT_DEPTH_SCALE).astype(np.uint16)
        if not (
            cv2.imwrite(str(folder / colour_name), bgr, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
            and cv2.imwrite(str(folder / depth_name), mm)
        ):
            raise DatasetError(f"cannot write frame {i} into {folder}")
        entry: dict = {"timestamp": frame.timestamp, "colour": colour_name, "depth": depth_name}
        pose = dataset.device_pose(i)
        if pose is not None:
            entry["T_device_camera"] = [float(v) for v in pose.reshape(-1)]
        frames.append(entry)
        if on_frame is not None:
            on_frame(i + 1, n)
    return replay_index(
        dataset.name, K, EXPORT_DEPTH_SCALE, gravity_in_first_camera(dataset), frames
    )


def replay_index(
    name: str,
    K: Intrinsics,
    depth_scale: float,
    gravity: list[float] | None,
    frames: list[dict],
) -> dict:
    """The page's replay index (``ReplaySequence.fromServer``): camera, sizes (colour and depth
    both K's, px), depth PNG units per metre, gravity in the first camera, the frames'
    ``{timestamp, colour, depth, ...}`` entries and their mean rate (15 fps when unknown)."""
    span = frames[-1]["timestamp"] - frames[0]["timestamp"] if frames else 0.0
    fps = (len(frames) - 1) / span if len(frames) > 1 and span > 0 else 15.0
    return {
        "name": name,
        "intrinsics": [K.fx, K.fy, K.cx, K.cy],
        "colour_size": [K.width, K.height],
        "depth_size": [K.width, K.height],
        "depth_scale": depth_scale,
        "depth_format": "png",
        "fps": round(float(fps), 3),
        "gravity": gravity,
        "frames": frames,
    }
