"""Colour-to-depth registration estimated from the images themselves.

Raw Kinect-style sensors deliver colour and depth from two cameras that are not registered to
each other: the colour camera has another focal length and sits a few centimetres beside the
depth camera. Read at a colour corner's pixel, the depth image then answers for another point,
and the tracker, back-projecting with the depth intrinsics, under-estimates rotation (7scenes_a:
by 13 %, benchmarks/README.md, "Drift"). Depth discontinuities are also edges in the colour
image; the mapping colour pixel -> depth pixel that lays the colour edges on the depth edges
gives ``DepthConfig.colour_focal_scale`` and ``colour_offset_*_px``. On registered images the
identity is best and nothing changes.

``ColourToDepth`` applies the mapping where frames come in (``track``, a live session): each
colour image is resampled onto the depth image's pixels, so that everything after it (corners
and their depth, place features, the map's colours) sees registered images with the depth
camera's intrinsics.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

from server.geometry import Intrinsics
from server.geometry.arrays import Float32Array, GreyImage
from server.registration.config import DepthConfig
from server.registration.preprocess import depth_to_colour_pixels, to_grey

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ColourRegistration:
    """Colour pixel u_c lies on depth pixel c + (u_c - c) / scale + (offset_u, offset_v)."""

    scale: float
    offset_u_px: float
    offset_v_px: float
    gain: float  # edge score of this mapping over the identity's


def estimate_colour_registration(
    grey: GreyImage,
    depth: Float32Array,
    K: Intrinsics,
    min_gain: float = 1.25,
    max_edge_pixels: int = 3000,
) -> ColourRegistration | None:
    """The mapping (focal scale 0.8-1.1, offsets up to 20 px) under which the colour image's
    gradient is strongest on the depth image's discontinuities; None when it beats the
    identity by less than ``min_gain`` (registered images, or too few depth edges to tell)."""
    g = grey.astype(np.float32)
    gm = np.hypot(cv2.Sobel(g, cv2.CV_32F, 1, 0), cv2.Sobel(g, cv2.CV_32F, 0, 1))
    d = np.nan_to_num(depth.astype(np.float32))
    dd = np.hypot(cv2.Sobel(d, cv2.CV_32F, 1, 0), cv2.Sobel(d, cv2.CV_32F, 0, 1))
    valid = cv2.erode((d > 0).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    v, u = np.nonzero(valid & (dd > 0.1 * np.maximum(d, 1e-3)))
    if len(u) < 200:
        return None
    step = max(1, len(u) // max_edge_pixels)
    u, v = u[::step].astype(np.float32), v[::step].astype(np.float32)
    h, w = grey.shape[:2]

    def score(s: float, du: float, dv: float) -> float:
        uc = K.cx + s * (u - du - K.cx)
        vc = K.cy + s * (v - dv - K.cy)
        ok = (uc >= 0) & (uc <= w - 1) & (vc >= 0) & (vc <= h - 1)
        if ok.sum() < 0.5 * len(u):
            return 0.0
        mu = uc[ok].astype(np.float32).reshape(1, -1)
        mv = vc[ok].astype(np.float32).reshape(1, -1)
        return float(cv2.remap(gm, mu, mv, cv2.INTER_LINEAR).mean())

    identity = score(1.0, 0.0, 0.0)
    best = (identity, 1.0, 0.0, 0.0)
    coarse = [
        (float(s), float(du), float(dv))
        for s in np.arange(0.80, 1.101, 0.02)
        for du in range(-20, 21, 4)
        for dv in range(-20, 21, 4)
    ]
    for s, du, dv in coarse:
        best = max(best, (score(s, du, dv), s, du, dv))
    _, s0, du0, dv0 = best
    fine = [
        (float(s0 + ds), float(du0 + a), float(dv0 + b))
        for ds in (-0.01, 0.0, 0.01)
        for a in range(-3, 4)
        for b in range(-3, 4)
    ]
    for s, du, dv in fine:
        best = max(best, (score(s, du, dv), s, du, dv))
    top, scale, offset_u, offset_v = best
    if identity <= 0 or top < min_gain * identity:
        return None
    return ColourRegistration(round(scale, 3), offset_u, offset_v, top / identity)


class ColourToDepth:
    """One stream's colour images registered to its depth images (the depth camera's pixels and
    intrinsics ``K``): by the mapping ``cfg`` gives (``colour_focal_scale``,
    ``colour_offset_*_px``), or, with ``cfg.estimate_colour_registration``, the one the first
    frame shows (``estimate_colour_registration``; kept only when clearly better than the
    identity). Registered streams pass through untouched, at no cost. ``estimate`` False: the
    stream's depth is known to be registered (a phone's, or depth much smaller than colour,
    whose upsampled blocks would only blur the edges the estimate needs): none is tried."""

    def __init__(self, K: Intrinsics, cfg: DepthConfig, estimate: bool = True) -> None:
        self.K = K
        given = (cfg.colour_focal_scale, cfg.colour_offset_u_px, cfg.colour_offset_v_px)
        self.mapping: ColourRegistration | None = (
            None if given == (1.0, 0.0, 0.0) else ColourRegistration(*given, gain=1.0)
        )
        self._estimate = estimate and cfg.estimate_colour_registration and self.mapping is None
        self._maps: tuple[tuple[int, int], np.ndarray, np.ndarray] | None = None

    def __call__(self, colour: np.ndarray, depth: Float32Array) -> np.ndarray:
        """``colour`` (H, W, 3) resampled onto the pixels of ``depth`` (H, W, metres, the same
        size), or ``colour`` itself when the stream is registered."""
        if self._estimate:
            self._estimate = False
            self.mapping = estimate_colour_registration(to_grey(colour), depth, self.K)
            if self.mapping is not None:
                log.info(
                    "colour not registered to depth: focal scale %.3f, offset (%.0f, %.0f) px "
                    "(edge score %.2fx the identity's); colour is resampled onto depth",
                    self.mapping.scale,
                    self.mapping.offset_u_px,
                    self.mapping.offset_v_px,
                    self.mapping.gain,
                )
        if self.mapping is None:
            return colour
        h, w = colour.shape[:2]
        if self._maps is None or self._maps[0] != (h, w):
            # Each depth pixel takes the colour pixel that sees it (preprocess's mapping).
            m = self.mapping
            cfg = DepthConfig(
                colour_focal_scale=m.scale,
                colour_offset_u_px=m.offset_u_px,
                colour_offset_v_px=m.offset_v_px,
            )
            v, u = np.mgrid[0:h, 0:w].astype(np.float64)
            uv = depth_to_colour_pixels(np.stack([u.ravel(), v.ravel()], 1), self.K, cfg)
            map_u = uv[:, 0].reshape(h, w).astype(np.float32)
            map_v = uv[:, 1].reshape(h, w).astype(np.float32)
            self._maps = ((h, w), map_u, map_v)
        _, map_u, map_v = self._maps
        return cv2.remap(colour, map_u, map_v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
