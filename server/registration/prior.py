"""The device's own camera pose as a prior: the initial guess it gives, and where its world lies.

A phone's visual-inertial odometry (ARCore, ARKit) reports T_device_camera: the camera's pose in
the device's own world frame, in metres, with this project's camera axes (x right, y down,
z forward). It is smooth from frame to frame but drifts over long spans, and its world frame is
not the map's. So the tracker uses only its motion since the last tracked frame (drift over the
span cancels), and keeps T_world_device, the device world's pose in the map, for whoever needs to
move between the two frames (the phone's overlay draws in the device's world).
"""

from __future__ import annotations

import logging
from collections import deque

import numpy as np

from server.geometry import invert, orthonormalize, rotation_angle_deg
from server.geometry.arrays import FloatArray
from server.registration.config import PriorConfig
from server.registration.results import Anchor, TrackResult

log = logging.getLogger(__name__)


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


class DevicePrior:
    """The tracker's use of the device's poses: each frame's prior checked, its guess for the
    frame (``guess``), and the device world's alignment to the map from frames tracked ok."""

    def __init__(self, config: PriorConfig) -> None:
        self.cfg = config
        self.alignment = DeviceAlignment(config)
        self.last: FloatArray | None = None  # the prior of the last tracked frame
        self.world = 0  # the device's world the priors are in (Tracker.track's device_world)

    def check(self, T_device_camera: FloatArray | None) -> FloatArray | None:
        """The prior to use for this frame, or None (none sent, disabled, or not finite)."""
        if T_device_camera is None or not self.cfg.enabled:
            return None
        T = np.asarray(T_device_camera, dtype=np.float64)
        if T.shape != (4, 4):
            raise ValueError(f"T_device_camera must be 4x4, got shape {T.shape}")
        if not np.isfinite(T).all():
            log.debug("non-finite device pose ignored")
            return None
        return orthonormalize(T)

    def enter_world(self, world: int) -> None:
        """The frame's prior is in the device's world number ``world``: a new one is a jump of
        the device's world, so the last prior and the alignment no longer hold."""
        if world != self.world:
            self.world = world
            self.reset()

    def guess(self, prior: FloatArray | None, T_world_last: FloatArray) -> FloatArray | None:
        """T_world_camera by the prior: its motion since the last tracked frame applied to that
        frame's pose (T_world_last, 4x4, metres); or, when that frame had no prior, the prior
        moved into the map."""
        if prior is None:
            return None
        if self.last is not None:
            motion = prior_motion(self.last, prior, self.cfg)
            if motion is not None:
                return orthonormalize(T_world_last @ motion)
            # The device's world jumped: its alignment to the map is void.
            log.info("device pose jumped: prior ignored, alignment reset")
            self.reset()
            return None
        T_world_device = self.alignment.T_world_device
        return None if T_world_device is None else orthonormalize(T_world_device @ prior)

    def resume(
        self, index: int, prior: FloatArray, T_world_prior: FloatArray, anchor: Anchor, lost: bool
    ) -> TrackResult | None:
        """No keyframe registers frame ``index`` (a gap in the frames, fast motion, blur), but the
        device still knows where it is: a new keyframe at the prior's pose (T_world_prior, 4x4,
        metres) lets tracking go on in the map. The device's drift since the last tracked frame
        (millimetres over a short gap) enters the map with it; staying lost until the user comes
        back to a mapped view would lose the rest of the session. The pose is WEAK. None (stay
        lost) when resuming is off or this frame cannot anchor tracking. ``lost``: the tracker
        was lost before this frame already."""
        if not self.cfg.resume_after_loss:
            return None
        if not lost:
            log.info("frame %d: no keyframe registers it; resumed from the device pose", index)
        result = anchor(T_world_prior, prior_used=True)
        if result is not None:
            self.last = prior
        return result

    def tracked(self, prior: FloatArray | None, T_world_camera: FloatArray, ok: bool) -> None:
        """A frame was tracked at T_world_camera with this prior (None: none); a frame tracked
        ``ok`` adds to the alignment."""
        self.last = prior
        if prior is not None and ok:
            self.alignment.add(T_world_camera, prior)

    def reset(self) -> None:
        """Forget the last prior and the alignment."""
        self.last = None
        self.alignment.reset()


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
