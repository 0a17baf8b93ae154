"""FAST corners on a scale pyramid, spread over the image (paper, section III-A)."""

from __future__ import annotations

import cv2
import numpy as np

from server.geometry.arrays import BoolArray, Float32Array, GreyImage
from server.registration.config import FeatureConfig


def detect_features(
    grey: GreyImage, cfg: FeatureConfig, mask: BoolArray | None = None
) -> Float32Array:
    """Corner positions (N, 2) as float32 (u, v) in full-resolution pixels, strongest first.

    Level l of the pyramid is the image shrunk by 2^l; its corners are scaled back to level 0.
    ``mask`` (H, W) bool, where given, keeps only corners on True pixels.
    """
    fast = cv2.FastFeatureDetector.create(threshold=cfg.fast_threshold, nonmaxSuppression=True)
    uvs, scores = [], []
    level: cv2.typing.MatLike = grey  # each pyrDown halves it
    for lvl in range(cfg.pyramid_levels):
        keypoints = fast.detect(level, None)
        if keypoints:
            scale = float(2**lvl)
            pts = np.array([kp.pt for kp in keypoints], dtype=np.float32)
            # A corner at pixel centre p of level l lies at (p + 0.5) * 2^l - 0.5 in level 0.
            uvs.append((pts + 0.5) * scale - 0.5)
            scores.append(np.array([kp.response for kp in keypoints], dtype=np.float32))
        level = cv2.pyrDown(level)
    if not uvs:
        return np.zeros((0, 2), np.float32)
    uv, score = np.concatenate(uvs), np.concatenate(scores)
    if mask is not None:
        h, w = mask.shape
        u = np.clip(np.rint(uv[:, 0]).astype(int), 0, w - 1)
        v = np.clip(np.rint(uv[:, 1]).astype(int), 0, h - 1)
        uv, score = uv[mask[v, u]], score[mask[v, u]]
    return spread_over_grid(uv, score, grey.shape, cfg)


def spread_over_grid(
    uv: Float32Array, score: Float32Array, shape: tuple[int, ...], cfg: FeatureConfig
) -> Float32Array:
    """Keep the strongest corners, at most an equal share per grid bucket and none closer than
    ``min_distance_px`` to a stronger one, so that the pose is constrained by the whole image."""
    h, w = shape[:2]
    order = np.argsort(-score, kind="stable")
    uv = uv[order]
    per_bucket = max(1, int(np.ceil(cfg.max_features / (cfg.grid_cols * cfg.grid_rows))))
    bucket = np.clip(
        (uv[:, 1] * cfg.grid_rows / h).astype(int), 0, cfg.grid_rows - 1
    ) * cfg.grid_cols + np.clip((uv[:, 0] * cfg.grid_cols / w).astype(int), 0, cfg.grid_cols - 1)
    # Rank of each corner within its bucket, by strength: drop those past the bucket's share.
    rank = np.zeros(len(uv), dtype=np.int64)
    seen: dict[int, int] = {}
    for i, b in enumerate(bucket):
        rank[i] = seen.get(b, 0)
        seen[b] = rank[i] + 1
    uv = uv[rank < per_bucket]
    # Suppress near-duplicates (the same corner found on several pyramid levels).
    cell = max(cfg.min_distance_px, 1.0)
    occupied = np.zeros((int(h / cell) + 2, int(w / cell) + 2), dtype=bool)
    keep = []
    for i, (u, v) in enumerate(uv):
        cu, cv_ = int(u / cell) + 1, int(v / cell) + 1
        if occupied[cv_, cu]:
            continue
        occupied[cv_ - 1 : cv_ + 2, cu - 1 : cu + 2] = True
        keep.append(i)
        if len(keep) >= cfg.max_features:
            break
    return uv[keep].astype(np.float32)
