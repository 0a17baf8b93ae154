"""A phone's own camera poses, simulated from a sequence's ground truth, to measure the tracker's
use of the device pose as a prior (benchmarks/registration.py, tests).

Visual-inertial odometry (ARCore, ARKit) is smooth from frame to frame but drifts: its path
stretches or bends by a few per cent of the distance travelled, and its heading (yaw, about
gravity) wanders by a fraction of a degree per second. It lives in its own world frame.
``drifting_device_poses`` builds such poses by integrating the ground truth's motion with those
errors added, plus small per-frame noise, and moves them into a different world frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from server.geometry import exp_se3, orthonormalize
from server.geometry.arrays import FloatArray


@dataclass(frozen=True)
class DeviceDrift:
    """How the simulated device pose departs from the truth (defaults: a typical phone's VIO)."""

    translation_fraction: float = 0.03  # drift per metre travelled, along a fixed direction
    yaw_deg_per_s: float = 0.6  # heading drift about the world's vertical (y) axis
    noise_m: float = 0.001  # per-frame translation noise, sigma per axis
    noise_deg: float = 0.05  # per-frame rotation noise, sigma per axis
    seed: int = 0


def device_world(seed: int = 0) -> FloatArray:
    """T_device_world: a fixed, seeded, arbitrary rotation (30-60 deg) and translation (~1 m)
    between the device's world frame and the sequence's, as a phone's own world would be."""
    rng = np.random.default_rng(seed + 1000)
    axis = rng.normal(size=3)
    angle = np.radians(rng.uniform(30.0, 60.0))
    return exp_se3(np.concatenate([axis / np.linalg.norm(axis) * angle, rng.normal(size=3)]))


def drifting_device_poses(
    T_world_camera: FloatArray, stamps: FloatArray, drift: DeviceDrift = DeviceDrift()
) -> FloatArray:
    """(N, 4, 4) T_device_camera for ground-truth poses (N, 4, 4) T_world_camera at ``stamps``
    (seconds): the true motion integrated with drift and noise, in the frame ``device_world``.

    Frame k's heading is off by yaw_deg_per_s * (t_k - t_0) and its position by
    translation_fraction of the path length so far (on top of the bent path), then noised.
    """
    rng = np.random.default_rng(drift.seed)
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    out = np.empty_like(T_world_camera)
    position = T_world_camera[0, :3, 3].copy()
    for k, (T, t) in enumerate(zip(T_world_camera, stamps, strict=True)):
        R_yaw = _yaw(np.radians(drift.yaw_deg_per_s * (t - stamps[0])))
        if k > 0:
            step = T[:3, 3] - T_world_camera[k - 1, :3, 3]
            position += R_yaw @ step + drift.translation_fraction * np.linalg.norm(step) * direction
        pose = np.eye(4)
        pose[:3, :3] = R_yaw @ T[:3, :3]
        pose[:3, 3] = position
        noise = np.concatenate(
            [
                rng.normal(scale=np.radians(drift.noise_deg), size=3),
                rng.normal(scale=drift.noise_m, size=3),
            ]
        )
        out[k] = orthonormalize(pose @ exp_se3(noise))
    T_device_world: FloatArray = device_world(drift.seed) @ out
    return T_device_world


def exact_device_poses(T_world_camera: FloatArray, seed: int = 0) -> FloatArray:
    """The ground truth moved into the device's world frame: a prior without drift or noise."""
    T_device_camera: FloatArray = device_world(seed) @ T_world_camera
    return T_device_camera


def _yaw(angle_rad: float) -> FloatArray:
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
