"""The last few processed camera frames, for the pilot's taps: ``goto_pixel`` names a pixel of
one of them, and the point it shows (read from the frame's depth) becomes the drone's target.

Poses are ``T_world_camera`` (4x4, metres, the client's world); depth is (H, W) metres at the
colour image's size, 0 where there is none; intrinsics ``fx, fy, cx, cy`` in pixels.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from server.geometry import Intrinsics
from server.sessions.errors import CommandRefused

PIXEL_WINDOW = 3  # half-size of the window a tapped pixel's depth is read from, px
RECENT_FRAMES = 8  # frames kept for goto_pixel


@dataclass
class CameraFrame:
    T_world_camera: np.ndarray
    depth: np.ndarray  # (H, W) metres at the colour image's size, 0 = none


class CameraFrames:
    """The RECENT_FRAMES newest frames by ``seq``. Thread-safe: its own lock (tracking adds
    frames and never waits for planning or physics), taking no other under it."""

    def __init__(self, K: Intrinsics, standoff_m: float) -> None:
        self.K = K
        self.standoff_m = standoff_m  # a tapped target stays this far in front of the surface
        self._lock = threading.Lock()
        self._frames: OrderedDict[int, CameraFrame] = OrderedDict()  # by seq, newest last

    def add(self, seq: int, T_world_camera: np.ndarray, depth: np.ndarray) -> None:
        with self._lock:
            self._frames.pop(seq, None)  # a reconnected client numbers from 0 again
            self._frames[seq] = CameraFrame(T_world_camera, depth)
            while len(self._frames) > RECENT_FRAMES:
                self._frames.popitem(last=False)

    def latest(self) -> tuple[int, np.ndarray] | None:
        """(seq, T_world_camera) of the newest frame."""
        with self._lock:
            if not self._frames:
                return None
            seq = next(reversed(self._frames))
            return seq, self._frames[seq].T_world_camera

    def move_with_world(self, T_correction: np.ndarray) -> None:
        """The world was corrected (loop closure; ``T_correction`` 4x4, old world to new): the
        frames move with it, so a tap on one from before still lands where it showed."""
        T = np.asarray(T_correction, dtype=np.float64)
        with self._lock:
            for frame in self._frames.values():
                frame.T_world_camera = T @ frame.T_world_camera

    def pixel_target(self, pixel, seq: int | None) -> np.ndarray:
        """The world point pixel ``(u, v)`` of frame ``seq`` (None: the newest) shows,
        standoff_m back towards the camera; raises CommandRefused (bad_command)."""
        with self._lock:
            if seq is None and self._frames:
                seq = next(reversed(self._frames))
            frame = None if seq is None else self._frames.get(seq)
        if frame is None:
            raise CommandRefused(
                "bad_command",
                f"frame {seq} is not among the last {RECENT_FRAMES} processed frames; tap again",
            )
        u, v = float(pixel[0]), float(pixel[1])
        h, w = frame.depth.shape
        if not (0 <= u < w and 0 <= v < h):
            raise CommandRefused(
                "bad_command", f"pixel ({u:.0f}, {v:.0f}) is outside the {w}x{h} image"
            )
        r = PIXEL_WINDOW
        window = frame.depth[
            max(0, int(v) - r) : int(v) + r + 1, max(0, int(u) - r) : int(u) + r + 1
        ]
        valid = window[(window > 0) & np.isfinite(window)]
        if valid.size == 0:
            raise CommandRefused(
                "bad_command",
                f"no depth at pixel ({u:.0f}, {v:.0f}); tap a surface the camera measured",
            )
        z = float(np.median(valid))
        K = self.K
        ray = np.array([(u - K.cx) / K.fx, (v - K.cy) / K.fy, 1.0])
        distance = z * np.linalg.norm(ray)
        back_off = min(self.standoff_m, 0.8 * distance)
        p_camera = ray / np.linalg.norm(ray) * (distance - back_off)
        T = frame.T_world_camera
        return T[:3, :3] @ p_camera + T[:3, 3]
