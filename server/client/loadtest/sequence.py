"""The load test's sequence: frames encoded once for the wire, played forward and backward."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from server import protocol as proto
from server.datasets import RGBDDataset
from server.errors import DroneSimError


class LoadTestError(DroneSimError):
    """The load test could not run at all (e.g. an empty sequence)."""


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
    size: tuple[int, int]  # width, height, px (colour and depth)
    frames: list[dict]

    @classmethod
    def from_dataset(
        cls,
        dataset: RGBDDataset,
        max_frames: int | None = None,
        depth_format: str = "zlib",
        workers: int = 4,
    ) -> EncodedSequence:
        n = len(dataset) if max_frames is None else min(max_frames, len(dataset))
        if n < 1:
            raise LoadTestError(f"{dataset.name} has no frames to stream")

        def encode(i: int) -> dict:
            frame = dataset[i]
            message = proto.make_frame(
                0,
                0.0,
                frame.colour,
                frame.depth,
                depth_format=depth_format,
                T_device_camera=dataset.device_pose(i),
            )
            del message["seq"], message["timestamp"]
            return message

        with ThreadPoolExecutor(workers) as pool:  # OpenCV releases the GIL while encoding
            frames = list(pool.map(encode, range(n)))
        K = dataset.intrinsics
        return cls(dataset.name, (K.fx, K.fy, K.cx, K.cy), (K.width, K.height), frames)

    def index(self, k: int) -> int:
        """Frame of capture k when playing forward, backward, forward, ... (ping-pong)."""
        return ping_pong_index(k, len(self.frames))

    @property
    def mean_bytes(self) -> float:
        return float(np.mean([len(f["colour"]) + len(f["depth"]) for f in self.frames]))
