"""Frame preprocessing: grey image, cleaned depth, and trusted depth at keypoints."""

from __future__ import annotations

from typing import cast

import cv2
import numpy as np

from server.geometry import Intrinsics
from server.geometry.arrays import Float32Array, FloatArray, GreyImage, RealArray
from server.registration.config import DepthConfig


def to_grey(colour: GreyImage) -> GreyImage:
    """(H, W, 3) RGB uint8 -> (H, W) uint8 intensity; a grey image passes through."""
    if colour.ndim == 2:
        return colour
    # OpenCV's stubs type every result as any numeric array; cvtColor keeps uint8.
    return cast(GreyImage, cv2.cvtColor(colour, cv2.COLOR_RGB2GRAY))


def clean_depth(depth: RealArray, cfg: DepthConfig) -> Float32Array:
    """Depth in metres with NaN, inf and out-of-range values set to 0 (= no measurement)."""
    d = np.asarray(depth, dtype=np.float32)
    # NaN fails both comparisons and inf the second: no separate isfinite pass needed.
    keep = (d >= cfg.min_depth_m) & (d <= cfg.max_depth_m)
    return np.where(keep, d, np.float32(0.0))


def axial_sigma(z: FloatArray, cfg: DepthConfig) -> FloatArray:
    """Standard deviation of a depth measurement along the optical axis, metres."""
    return cfg.axial_noise_a_m + cfg.axial_noise_b_per_m * (z - 0.4) ** 2


def sample_stable_depth(depth: Float32Array, uv: Float32Array, cfg: DepthConfig) -> Float32Array:
    """Depth (N,) in metres at pixels ``uv`` (N, 2), or 0 where it cannot be trusted.

    A depth is trusted when the whole 3x3 neighbourhood is measured and its spread is small:
    near depth edges a sub-pixel keypoint error (or colour/depth misregistration) would pick
    the wrong surface.
    """
    h, w = depth.shape
    u = np.rint(uv[:, 0]).astype(np.int64)
    v = np.rint(uv[:, 1]).astype(np.int64)
    inside = (u >= 1) & (u < w - 1) & (v >= 1) & (v < h - 1)
    u, v = np.where(inside, u, 1), np.where(inside, v, 1)
    patch = np.stack([depth[v + dv, u + du] for dv in (-1, 0, 1) for du in (-1, 0, 1)], axis=1)
    lo, hi = patch.min(axis=1), patch.max(axis=1)
    centre = patch[:, 4]
    stable = inside & (lo > 0) & (hi - lo <= cfg.max_local_depth_spread * centre)
    # The median of the neighbourhood is less noisy than the centre pixel alone.
    return np.where(stable, np.median(patch, axis=1), 0.0)


def resample_depth(depth: Float32Array, width: int, height: int) -> Float32Array:
    """Depth (h, w) resized to (height, width) by nearest neighbour: phone depth is often much
    smaller than colour, and interpolating across an edge would invent surfaces in mid-air."""
    if depth.shape == (height, width):
        return depth
    # cv2.resize keeps the dtype; its stubs do not say so.
    return cast(Float32Array, cv2.resize(depth, (width, height), interpolation=cv2.INTER_NEAREST))


def colour_to_depth_pixels(uv: Float32Array, K: Intrinsics, cfg: DepthConfig) -> Float32Array:
    """Depth-image pixels (N, 2) of colour pixels ``uv`` (N, 2) when colour and depth differ in
    focal length (cfg.colour_focal_scale = colour focal / depth focal)."""
    s = cfg.colour_focal_scale
    d = np.array([cfg.colour_offset_u_px, cfg.colour_offset_v_px], dtype=np.float32)
    if s == 1.0 and not d.any():
        return uv
    c = np.array([K.cx, K.cy], dtype=np.float32)
    return cast(Float32Array, (c + (uv - c) / np.float32(s) + d).astype(np.float32))


def depth_to_colour_pixels(uv: FloatArray, K: Intrinsics, cfg: DepthConfig) -> FloatArray:
    """The inverse of :func:`colour_to_depth_pixels`: colour pixels (N, 2) of depth pixels."""
    s = cfg.colour_focal_scale
    d = np.array([cfg.colour_offset_u_px, cfg.colour_offset_v_px])
    if s == 1.0 and not d.any():
        return uv
    c = np.array([K.cx, K.cy])
    out: FloatArray = c + (uv - d - c) * s
    return out
