"""The device's own camera pose as a prior: the initial guess it gives, and where its world lies.

A phone's visual-inertial odometry (ARCore, ARKit) reports T_device_camera: the camera's pose in
the device's own world frame, in metres, with this project's camera axes (x right, y down,
z forward). It is smooth from frame to frame but drifts over long spans, and its world frame is
not the map's. So the tracker uses only its motion since the last tracked frame (drift over the
span cancels), and keeps T_world_device, the device world's pose in the map, for whoever needs to
move between the two frames (the phone's overlay draws in the device's world).
"""

from __future__ import annotations

from collections import deque

import numpy as np

from server.geometry import invert, orthonormalize, rotation_angle_deg
from server.geometry.arrays import FloatArray
from server.registration.config import PriorConfig


def prior_motion(
    T_device_last: FloatArray, T_device_cur: FloatArray, config: PriorConfig
) -> FloatArray | None:
    """T_last_cur, the camera's motion by the prior since the last tracked frame; None when it is
    too large to be motion (the device's own tracking was reset, or the prior is corrupt)."""
    motion = invert(T_device_last) @ T_device_cur
    if (
        float(np.linalg.norm(motion[:3, 3])) > config.max_motion_m
        or rotation_angle_deg(motion) > config.max_motion_deg
    ):
        return None
    return motion


class DeviceAlignment:
    """T_world_device, the device's world frame in the map (the tracker's world), from frames
    that tracked well.

    Each such frame gives one estimate, T_world_camera @ inv(T_device_camera). A drifting prior
    makes them wander slowly and a poorly tracked frame makes one jump, so only the latest
    ``config.alignment_frames`` are kept and combined robustly: those far from the median
    (rotation or translation) are dropped, the rest averaged (chordal mean of the rotations).
    """

    def __init__(self, config: PriorConfig) -> None:
        self.estimates: deque[FloatArray] = deque(maxlen=config.alignment_frames)
        self.T_world_device: FloatArray | None = None

    def add(self, T_world_camera: FloatArray, T_device_camera: FloatArray) -> None:
        self.estimates.append(orthonormalize(T_world_camera @ invert(T_device_camera)))
        self.T_world_device = _robust_mean(np.array(self.estimates))

    def reset(self) -> None:
        """Forget the alignment: the device's world frame has changed (its tracking restarted)."""
        self.estimates.clear()
        self.T_world_device = None


def _robust_mean(Ts: FloatArray) -> FloatArray:
    """Mean of (N, 4, 4) rigid transforms without those beyond 3x the median spread."""
    t = Ts[:, :3, 3]
    R_all = _chordal_mean(Ts[:, :3, :3])
    angle = np.array([rotation_angle_deg(_as_T(R_all.T @ R)) for R in Ts[:, :3, :3]])
    dist = np.linalg.norm(t - np.median(t, axis=0), axis=1)
    # The small floors keep identical estimates (an exact prior) from rejecting each other.
    keep = (angle <= 3.0 * np.median(angle) + 1e-6) & (dist <= 3.0 * np.median(dist) + 1e-6)
    out = np.eye(4)
    out[:3, :3] = _chordal_mean(Ts[keep, :3, :3])
    out[:3, 3] = t[keep].mean(axis=0)
    return out


def _chordal_mean(Rs: FloatArray) -> FloatArray:
    """The rotation nearest (Frobenius) to the mean of (N, 3, 3) rotation matrices."""
    return orthonormalize(_as_T(Rs.mean(axis=0)))[:3, :3]


def _as_T(R: FloatArray) -> FloatArray:
    T = np.eye(4)
    T[:3, :3] = R
    return T
