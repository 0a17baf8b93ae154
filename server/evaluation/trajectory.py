"""Trajectories: timestamped camera poses, their matching by timestamp, and TUM files (one
read/write pair). Datasets (ground truth), sessions and metrics all use these.

TUM format: one pose per line, ``timestamp tx ty tz qx qy qz qw`` (seconds, metres, unit
quaternion), ``#`` starts a comment line. Poses are T_world_camera.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from server.atomic import atomic_write
from server.errors import TrajectoryError
from server.geometry import pose_from_quaternion, quaternion_from_pose
from server.textfile import data_lines

logger = logging.getLogger(__name__)

TUM_FORMAT = "'timestamp tx ty tz qx qy qz qw' (8 numbers per line, '#' for comments)"


@dataclass
class Trajectory:
    """Timestamped poses: ``timestamps`` (N,) seconds, ``poses`` (N, 4, 4) T_world_camera,
    metres."""

    timestamps: np.ndarray
    poses: np.ndarray

    def __len__(self) -> int:
        return len(self.timestamps)


def associate(
    a_stamps: np.ndarray, b_stamps: np.ndarray, max_diff: float
) -> tuple[np.ndarray, np.ndarray]:
    """One-to-one nearest-timestamp matching, greedy by smallest time difference (TUM associate.py).

    a_stamps, b_stamps: timestamps in seconds, any order. max_diff: largest accepted |a - b| in s.
    Returns index arrays (idx_a, idx_b), sorted by idx_a; both empty when nothing matches.
    """
    a = np.asarray(a_stamps, dtype=np.float64)
    b = np.asarray(b_stamps, dtype=np.float64)
    order = np.argsort(b, kind="stable")
    b_sorted = b[order]
    lo = np.searchsorted(b_sorted, a - max_diff, side="left")
    hi = np.searchsorted(b_sorted, a + max_diff, side="right")
    candidates = []  # (|diff|, i, j) for every pair within the tolerance
    for i in range(len(a)):
        for k in range(lo[i], hi[i]):
            j = int(order[k])
            diff = abs(a[i] - b[j])
            if diff <= max_diff:
                candidates.append((diff, i, j))
    candidates.sort()
    used_a, used_b, pairs = set(), set(), []
    for _, i, j in candidates:
        if i not in used_a and j not in used_b:
            used_a.add(i)
            used_b.add(j)
            pairs.append((i, j))
    pairs.sort()
    idx = np.array(pairs, dtype=np.int64).reshape(-1, 2)
    return idx[:, 0], idx[:, 1]


def _parse_row(path: Path, line_no: int, line: str) -> tuple[float, np.ndarray]:
    """One TUM row -> (timestamp s, T_world_camera 4x4); TrajectoryError naming file and line."""
    fields = line.replace(",", " ").split()
    if len(fields) != 8:
        raise TrajectoryError(
            f"{path}:{line_no}: expected 8 columns {TUM_FORMAT}, got {len(fields)}: {line!r}"
        )
    try:
        values = np.array([float(f) for f in fields])
    except ValueError as exc:
        raise TrajectoryError(f"{path}:{line_no}: not a number in {line!r} ({exc})") from exc
    if not np.all(np.isfinite(values)):
        raise TrajectoryError(f"{path}:{line_no}: non-finite value in {line!r}")
    q = values[4:8]
    if np.linalg.norm(q) < 1e-6:
        raise TrajectoryError(f"{path}:{line_no}: zero quaternion in {line!r}")
    return float(values[0]), pose_from_quaternion(values[1:4], q)


def read_tum(path: str | Path) -> Trajectory:
    """Read a TUM trajectory file into a Trajectory (timestamps s, poses T_world_camera, metres).

    Raises TrajectoryError if the file is missing, empty, or has a malformed row (the message names
    the file and the line number).
    """
    path = Path(path)
    stamps, poses = [], []
    for line_no, line in data_lines(path, TrajectoryError, "trajectory file "):
        stamp, pose = _parse_row(path, line_no, line)
        stamps.append(stamp)
        poses.append(pose)
    if not stamps:
        raise TrajectoryError(f"{path}: no poses found; expected rows {TUM_FORMAT}")
    timestamps = np.array(stamps)
    if np.any(np.diff(timestamps) < 0):
        logger.warning("%s: timestamps are not sorted", path)
    logger.debug("read %d poses from %s", len(stamps), path)
    return Trajectory(timestamps=timestamps, poses=np.stack(poses))


def write_tum(path: str | Path, traj: Trajectory) -> None:
    """Write ``traj`` as a TUM trajectory file, atomically (temp file in the same folder + rename).

    Timestamps get 6 decimals (microseconds), translations 9 (nanometres), quaternions have w >= 0.
    """
    path = Path(path)
    timestamps = np.asarray(traj.timestamps, dtype=np.float64)
    poses = np.asarray(traj.poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or len(poses) != len(timestamps):
        raise TrajectoryError(
            f"cannot write {path}: need N timestamps and (N, 4, 4) poses, "
            f"got {timestamps.shape} and {poses.shape}"
        )
    lines = ["# timestamp tx ty tz qx qy qz qw (T_world_camera, metres)"]
    for stamp, T in zip(timestamps, poses, strict=True):
        numbers = [*T[:3, 3], *quaternion_from_pose(T)]
        lines.append(f"{stamp:.6f} " + " ".join(f"{v:.9f}" for v in numbers))
    text = "\n".join(lines) + "\n"
    atomic_write(path, lambda tmp: Path(tmp).write_text(text))
    logger.debug("wrote %d poses to %s", len(timestamps), path)
