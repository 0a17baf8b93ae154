"""The load test's sequence: frames encoded once for the wire, played forward and backward."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np

from server import protocol as proto
from server.datasets import RGBDDataset
from server.errors import DroneSimError


class LoadTestError(DroneSimError):
    """The load test could not run at all (e.g. an empty sequence)."""


@dataclass(frozen=True)
class FrameProfile:
    """The frames a kind of phone sends, made from a recorded sequence's: the colour cropped
    about its centre to ``aspect`` (width / height; None: as recorded) and scaled to
    ``colour_long`` px on its long side, the depth at the colour's aspect with ``depth_long`` px
    on its long side (None: the recorded size; depth is resampled by nearest neighbour)."""

    name: str
    aspect: float | None = None
    colour_long: int | None = None
    depth_long: int | None = None


# What the phone page and the recording import send (docs/LIVE_AR.md): a Kinect-like 640x480
# RGB-D camera; ARCore in live AR on a 20:9 phone (colour 640 px long at the screen's aspect,
# depth at the colour's aspect from the 160 px depth buffer); an iPhone recording replayed
# (640x480 colour, LiDAR's 256x192 depth).
FRAME_PROFILES = {
    p.name: p
    for p in (
        FrameProfile("kinect"),
        FrameProfile("arcore", aspect=20 / 9, colour_long=640, depth_long=160),
        FrameProfile("iphone", aspect=4 / 3, colour_long=640, depth_long=256),
    )
}


def _crop_box(width: int, height: int, aspect: float | None) -> tuple[int, int, int, int]:
    """(x0, y0, w, h): the largest centred crop of a width x height image at ``aspect``."""
    if aspect is None:
        return 0, 0, width, height
    w, h = (
        (round(height * aspect), height)
        if width / height > aspect
        else (width, round(width / aspect))
    )
    return (width - w) // 2, (height - h) // 2, w, h


def _scaled(size: tuple[int, int], long_side: int | None) -> tuple[int, int]:
    if long_side is None:
        return size
    s = long_side / max(size)
    return round(size[0] * s), round(size[1] * s)


def ping_pong_index(k: int, n: int) -> int:
    """Which of n frames capture k shows when a sequence plays forward, backward, forward, ...
    (looping that way keeps the camera's motion continuous)."""
    if n == 1:
        return 0
    k %= 2 * n - 2
    return k if k < n else 2 * n - 2 - k


@dataclass
class EncodedSequence:
    """A sequence encoded once for the wire: frame messages without seq and timestamp. A phone's
    recording (``dataset.device_poses``) gives each frame its ``T_device_camera``."""

    name: str
    intrinsics: tuple[float, float, float, float]  # fx, fy, cx, cy of the colour image, px
    size: tuple[int, int]  # the colour's width, height, px
    frames: list[dict]
    depth_size: tuple[int, int] | None = None  # the depth's, px (None: the colour's)
    profile: str = "kinect"

    @classmethod
    def from_dataset(
        cls,
        dataset: RGBDDataset,
        max_frames: int | None = None,
        depth_format: str = "zlib",
        workers: int = 4,
        profile: str | FrameProfile = "kinect",
    ) -> EncodedSequence:
        """The first ``max_frames`` frames of ``dataset`` as ``profile`` (FRAME_PROFILES) sends
        them. Cropping and scaling keep the camera: the intrinsics move with the crop and scale
        with the colour; the depth is the colour's view at its own size."""
        n = len(dataset) if max_frames is None else min(max_frames, len(dataset))
        if n < 1:
            raise LoadTestError(f"{dataset.name} has no frames to stream")
        p = FRAME_PROFILES[profile] if isinstance(profile, str) else profile
        K = dataset.intrinsics
        x0, y0, cw, ch = _crop_box(K.width, K.height, p.aspect)
        colour_size = _scaled((cw, ch), p.colour_long)
        depth_size = _scaled(colour_size, p.depth_long)
        s = colour_size[0] / cw
        # Pixel centres at integers: a crop shifts the principal point, a scale by s maps
        # c to (c + 0.5) s - 0.5.
        cx, cy = (K.cx - x0 + 0.5) * s - 0.5, (K.cy - y0 + 0.5) * s - 0.5

        def encode(i: int) -> dict:
            frame = dataset[i]
            colour = frame.colour[y0 : y0 + ch, x0 : x0 + cw]
            depth = frame.depth[y0 : y0 + ch, x0 : x0 + cw]
            if colour_size != (cw, ch):
                colour = cv2.resize(colour, colour_size, interpolation=cv2.INTER_AREA)
            if depth_size != (cw, ch):
                depth = cv2.resize(depth, depth_size, interpolation=cv2.INTER_NEAREST)
            message = proto.make_frame(
                0,
                0.0,
                np.ascontiguousarray(colour),
                np.ascontiguousarray(depth),
                depth_format=depth_format,
                T_device_camera=dataset.device_pose(i),
            )
            del message["seq"], message["timestamp"]
            return message

        with ThreadPoolExecutor(workers) as pool:  # OpenCV releases the GIL while encoding
            frames = list(pool.map(encode, range(n)))
        return cls(
            dataset.name,
            (K.fx * s, K.fy * s, cx, cy),
            colour_size,
            frames,
            depth_size=depth_size,
            profile=p.name,
        )

    def index(self, k: int) -> int:
        """Frame of capture k when playing forward, backward, forward, ... (ping-pong)."""
        return ping_pong_index(k, len(self.frames))

    def start(self, session: int, sessions: int) -> int:
        """The capture (``index``'s k) that session ``session`` of ``sessions`` starts at: the
        sessions spread evenly over one forward-and-back cycle, so that phones replaying one
        sequence are each somewhere else in it, as phones in a room would be. Played in step,
        each hard stretch (a fast turn, a run of keyframes) reaches every session at once."""
        cycle = max(1, 2 * len(self.frames) - 2)
        return session * cycle // max(1, sessions)

    @property
    def mean_bytes(self) -> float:
        return float(np.mean([len(f["colour"]) + len(f["depth"]) for f in self.frames]))
