"""Pinhole camera model: the paper's projection pi (eq. 1) and its inverse (eq. 2).

Camera frame convention: x right, y down, z forward (optical axis), metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from server.errors import ConfigError
from server.geometry.arrays import FloatArray, RealArray


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels for an image of ``width`` x ``height`` pixels."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def __post_init__(self) -> None:
        values = (self.fx, self.fy, self.cx, self.cy)
        if not all(np.isfinite(values)) or self.fx <= 0 or self.fy <= 0:
            raise ConfigError(f"intrinsics need finite positive focal lengths, got {values}")
        if self.width <= 0 or self.height <= 0:
            raise ConfigError(f"image size must be positive, got {self.width}x{self.height}")

    @property
    def matrix(self) -> FloatArray:
        """The 3x3 calibration matrix K."""
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    def scaled(self, factor: float) -> Intrinsics:
        """Intrinsics of the same camera with the image resized by ``factor`` (0.5 = half size).

        Uses the pixel-centre convention: a pixel centre at u maps to (u + 0.5) * factor - 0.5.
        """
        return Intrinsics(
            fx=self.fx * factor,
            fy=self.fy * factor,
            cx=(self.cx + 0.5) * factor - 0.5,
            cy=(self.cy + 0.5) * factor - 0.5,
            width=int(round(self.width * factor)),
            height=int(round(self.height * factor)),
        )


def backproject_pixels(uv: FloatArray, depth: RealArray, K: Intrinsics) -> FloatArray:
    """Eq. 1: pixels ``uv`` (N, 2) with depths ``depth`` (N,) in metres -> points (N, 3) in
    metres."""
    z = np.asarray(depth, dtype=np.float64)
    x = (uv[:, 0] - K.cx) * z / K.fx
    y = (uv[:, 1] - K.cy) * z / K.fy
    return np.stack([x, y, z], axis=1)


def backproject(depth: RealArray, K: Intrinsics, stride: int = 1) -> tuple[FloatArray, FloatArray]:
    """Back-project every ``stride``-th pixel of a depth image (H, W) in metres.

    Returns (points (N, 3) in the camera frame, pixel indices (N, 2) as (u, v)) for valid depth
    only.
    """
    d = depth[::stride, ::stride]
    v, u = np.nonzero(np.isfinite(d) & (d > 0))
    uv = np.stack([u * stride, v * stride], axis=1).astype(np.float64)
    return backproject_pixels(uv, d[v, u], K), uv


def project(points: FloatArray, K: Intrinsics) -> tuple[FloatArray, FloatArray]:
    """Eq. 2: camera-frame points (N, 3) -> (pixels (N, 2), depths (N,)). Points behind the camera
    get NaN pixels."""
    z = points[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_z = np.where(z > 1e-9, 1.0 / z, np.nan)
    u = points[:, 0] * K.fx * inv_z + K.cx
    v = points[:, 1] * K.fy * inv_z + K.cy
    return np.stack([u, v], axis=1), z
