"""A hands-off pilot for replayed sessions: it keeps the drone touring the mapped room.

Targets are places the camera looked at from close by (a little ahead of past camera poses):
space the map has seen free. An unreachable target is swapped for the nearest reachable point
the server suggests; after a few refusals in a row the pilot waits for more of the map. While a
course runs (a ``course`` message in state running) it keeps its hands off the drone.
"""

from __future__ import annotations

import numpy as np

from server import protocol as proto

AHEAD_M = 0.7  # targets lie this far in front of a past camera
MAX_REFUSALS = 3  # refused targets in a row before waiting for more map
WAIT_POSES = 15  # poses to wait for after that


class TourPilot:
    """Call with every server message; returns the next command to send, or None."""

    def __init__(self, seed: int = 0) -> None:
        self.rng = np.random.default_rng(seed)
        self.cameras: list[np.ndarray] = []
        self.next_id = 1
        self.refusals = 0
        self.resume_at: int | None = None  # number of cameras after which to fly again
        self.course_running = False

    def __call__(self, msg: dict) -> dict | None:
        kind = msg["type"]
        if kind == "course":
            self.course_running = msg["state"] == "running"
            return None
        if self.course_running:
            if kind == "pose" and msg["state"] != "lost":
                T = proto.pose_matrix(msg)
                self.cameras.append(T[:3, 3] + AHEAD_M * T[:3, 2])
            return None
        if kind == "pose" and msg["state"] != "lost":
            T = proto.pose_matrix(msg)
            self.cameras.append(T[:3, 3] + AHEAD_M * T[:3, 2])
            if self.resume_at is not None and len(self.cameras) >= self.resume_at:
                self.resume_at = None
                return self._goto(self._pick())
        elif kind == "drone_event" and msg["event"] in (
            "spawned",
            "arrived",
            "blocked",
            "collision",
        ):
            self.refusals = 0
            return self._goto(self._pick())
        elif kind == "drone_event" and msg["event"] == "landed":  # after a crash: fly on
            self.resume_at = len(self.cameras) + WAIT_POSES
            self.next_id += 1
            return proto.make_command(self.next_id, "takeoff")
        elif kind == "error" and msg.get("command_id") is not None:
            self.refusals += 1
            if self.refusals >= MAX_REFUSALS:
                self.refusals, self.resume_at = 0, len(self.cameras) + WAIT_POSES
                return None
            if "nearest" in msg:
                return self._goto(np.asarray(msg["nearest"]))
            return self._goto(self._pick())
        return None

    def _pick(self) -> np.ndarray | None:
        if not self.cameras:
            return None
        return self.cameras[self.rng.integers(len(self.cameras))]

    def _goto(self, target: np.ndarray | None) -> dict | None:
        if target is None:
            return None
        self.next_id += 1
        return proto.make_command(self.next_id, "goto", target=target, speed=0.8)
