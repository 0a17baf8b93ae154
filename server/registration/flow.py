"""Pyramidal Lucas-Kanade tracking with a forward-backward check (paper, section III-A)."""

from __future__ import annotations

from typing import cast

import cv2
import numpy as np

from server.geometry.arrays import BoolArray, Float32Array, GreyImage, RealArray
from server.registration.config import FlowConfig


def track_points(
    grey_from: GreyImage,
    grey_to: GreyImage,
    uv_from: Float32Array,
    cfg: FlowConfig,
    uv_guess: RealArray | None = None,
) -> tuple[Float32Array, BoolArray]:
    """Track pixels ``uv_from`` (N, 2) of ``grey_from`` into ``grey_to``.

    ``uv_guess`` (N, 2), e.g. from a motion prediction, starts the search there; under fast
    rotation this keeps the flow within reach of the pyramid.
    Returns (uv_to (N, 2) float32, ok (N,) bool): ok only where both directions converged and
    tracking back lands within ``max_fb_error_px`` of the start.
    """
    n = len(uv_from)
    if n == 0:
        return np.zeros((0, 2), np.float32), np.zeros(0, bool)
    p0 = np.ascontiguousarray(uv_from, dtype=np.float32).reshape(-1, 1, 2)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, cfg.max_iterations, cfg.epsilon)
    win = (cfg.window_px, cfg.window_px)
    flags = 0
    # Without a guess, OpenCV allocates the output points itself.
    start: Float32Array | None = None
    if uv_guess is not None:
        start = np.ascontiguousarray(uv_guess, dtype=np.float32).reshape(-1, 1, 2).copy()
        flags = cv2.OPTFLOW_USE_INITIAL_FLOW
    p1, st1, _ = cv2.calcOpticalFlowPyrLK(
        grey_from,
        grey_to,
        p0,
        start,  # type: ignore[arg-type, unused-ignore]  # None is valid; stubs before 5.1 omit it
        winSize=win,
        maxLevel=cfg.pyramid_levels,
        criteria=criteria,
        flags=flags,
    )
    # Back from where the forward pass ended, starting at the original corner: a right track
    # returns there, so the check needs few pyramid levels (each costs a full LK pass).
    p0_back, st2, _ = cv2.calcOpticalFlowPyrLK(
        grey_to,
        grey_from,
        p1,
        p0.copy(),
        winSize=win,
        maxLevel=min(cfg.fb_pyramid_levels, cfg.pyramid_levels),
        criteria=criteria,
        flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
    )
    uv_to = cast(Float32Array, p1.reshape(-1, 2))  # float32 like p0, whatever the stubs say
    fb_error = np.linalg.norm(p0_back.reshape(-1, 2) - p0.reshape(-1, 2), axis=1)
    h, w = grey_to.shape[:2]
    inside = (
        (uv_to[:, 0] >= 0) & (uv_to[:, 0] <= w - 1) & (uv_to[:, 1] >= 0) & (uv_to[:, 1] <= h - 1)
    )
    ok = (st1.ravel() == 1) & (st2.ravel() == 1) & (fb_error < cfg.max_fb_error_px) & inside
    return uv_to, ok
