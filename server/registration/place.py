"""Place recognition: ORB descriptors with depth per keyframe, and a database that finds the
keyframes a new frame may see.

A frame with no pose guess (opening a saved room, or a loop back to an old view) cannot be
tracked by optical flow; its binary descriptors can still be matched against every keyframe's.
The database only proposes candidates; :mod:`server.registration.verify` decides.

Look-up: all keyframes' descriptors are stacked, each query descriptor finds its nearest one by
brute-force Hamming distance (one OpenCV call) and votes for that keyframe; the keyframes with
the most votes are the candidates. On 7scenes_a it found the same places as verifying every
keyframe, at a quarter of the time (benchmarks/README.md, "Rooms").
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from server.geometry import Intrinsics, backproject_pixels
from server.geometry.arrays import Float32Array, FloatArray, GreyImage
from server.registration.config import DepthConfig, PlaceConfig
from server.registration.preprocess import sample_stable_depth

Descriptors = NDArray[np.uint8]  # (N, 32): 256-bit ORB descriptors


@dataclass
class PlaceFeatures:
    """ORB features of one image that have trusted depth.

    uv: (N, 2) pixels; descriptors: (N, 32) uint8; points: (N, 3) back-projected in this image's
    camera frame, metres. depth: (h, w) metres (0 = none), the image's depth shrunk by
    ``cfg.depth_shrink`` (nearest of each block), seen with ``intrinsics``: what verification
    compares surfaces with.
    """

    uv: Float32Array
    descriptors: Descriptors
    points: FloatArray
    depth: Float32Array
    intrinsics: Intrinsics

    def __len__(self) -> int:
        return len(self.uv)


def describe_place(
    grey: GreyImage, depth: Float32Array, K: Intrinsics, cfg: PlaceConfig, depth_cfg: DepthConfig
) -> PlaceFeatures:
    """ORB keypoints and descriptors of ``grey`` (H, W uint8) kept where ``depth`` (H, W,
    metres, cleaned: 0 = none) is trusted, with their 3D points (camera frame, metres)."""
    small, K_small = depth_thumbnail(depth, K, cfg.depth_shrink)
    orb = cv2.ORB.create(nfeatures=cfg.orb_features)
    keypoints, descriptors = orb.detectAndCompute(grey, None)
    if descriptors is None or not keypoints:
        return PlaceFeatures(
            np.zeros((0, 2), np.float32),
            np.zeros((0, 32), np.uint8),
            np.zeros((0, 3)),
            small,
            K_small,
        )
    uv = np.array([kp.pt for kp in keypoints], dtype=np.float32)
    z = sample_stable_depth(depth, uv, depth_cfg)
    keep = z > 0
    points = backproject_pixels(uv[keep].astype(np.float64), z[keep], K)
    return PlaceFeatures(uv[keep], np.ascontiguousarray(descriptors[keep]), points, small, K_small)


def depth_thumbnail(
    depth: Float32Array, K: Intrinsics, shrink: int
) -> tuple[Float32Array, Intrinsics]:
    """Every ``shrink``-th pixel of ``depth`` (metres; the centre of each block, no averaging
    across edges) and the intrinsics it is seen with."""
    small = np.ascontiguousarray(depth[shrink // 2 :: shrink, shrink // 2 :: shrink])
    # Pixel (i, j) of the thumbnail is pixel (shrink * i + shrink // 2, ...) of the image.
    o = shrink // 2
    K_small = Intrinsics(
        K.fx / shrink, K.fy / shrink, (K.cx - o) / shrink, (K.cy - o) / shrink,
        small.shape[1], small.shape[0],
    )  # fmt: skip
    return small, K_small


@dataclass
class PlaceEntry:
    """One keyframe in the database: its id, pose T_world_keyframe (4x4, metres) and features."""

    keyframe_id: int
    T_world_keyframe: FloatArray
    features: PlaceFeatures


@dataclass
class KeyframeDatabase:
    """Keyframes' place features, searchable by a new image's descriptors."""

    entries: list[PlaceEntry] = field(default_factory=list)
    _stacked: Descriptors | None = None  # all descriptors, rebuilt after an add
    _owner: NDArray[np.intp] | None = None  # entry index of each stacked descriptor

    def __len__(self) -> int:
        return len(self.entries)

    def add(self, keyframe_id: int, T_world_keyframe: FloatArray, features: PlaceFeatures) -> None:
        self.entries.append(PlaceEntry(keyframe_id, T_world_keyframe.copy(), features))
        self._stacked = self._owner = None

    def entry(self, keyframe_id: int) -> PlaceEntry:
        for e in self.entries:
            if e.keyframe_id == keyframe_id:
                return e
        raise KeyError(keyframe_id)

    def set_pose(self, keyframe_id: int, T_world_keyframe: FloatArray) -> None:
        """Move a keyframe (after a pose-graph correction)."""
        self.entry(keyframe_id).T_world_keyframe = T_world_keyframe.copy()

    def candidates(
        self,
        query: PlaceFeatures,
        cfg: PlaceConfig,
        allowed: set[int] | None = None,
    ) -> list[tuple[int, int]]:
        """Up to ``cfg.candidates`` (keyframe_id, votes), most votes first, with at least
        ``cfg.min_votes``. ``allowed``: only these keyframe ids may be returned (e.g. those older
        than a loop's minimum age); None for all."""
        entries = [e for e in self.entries if allowed is None or e.keyframe_id in allowed]
        if len(query) == 0 or not entries:
            return []
        # Only allowed keyframes vote: a newer one that sees the same corner would otherwise
        # take the vote that a loop's old keyframe needs.
        if allowed is None:
            if self._stacked is None or self._owner is None:
                self._stacked, self._owner = _stack(entries, cfg.vote_features)
            stacked, owner = self._stacked, self._owner
        else:
            stacked, owner = _stack(entries, cfg.vote_features)
        if len(stacked) == 0:
            return []
        matcher = cv2.BFMatcher.create(cv2.NORM_HAMMING)
        # A subset of the descriptors on both sides: the look-up's cost grows with their product
        # (OpenCV's brute-force Hamming matcher, one thread).
        step = max(1, len(query) // cfg.vote_features)
        matches = matcher.match(query.descriptors[::step], stacked)
        owners = [int(owner[m.trainIdx]) for m in matches if m.distance <= cfg.vote_max_hamming]
        votes = np.bincount(np.asarray(owners, np.intp), minlength=len(entries))
        ranked = []
        for i in np.argsort(-votes, kind="stable"):
            if votes[i] < cfg.min_votes:
                break
            ranked.append((entries[i].keyframe_id, int(votes[i])))
            if len(ranked) == cfg.candidates:
                break
        return ranked


def _stack(entries: list[PlaceEntry], per_entry: int) -> tuple[Descriptors, NDArray[np.intp]]:
    """Up to ``per_entry`` descriptors of each entry (evenly picked) in one array, and the entry
    index of each."""
    picked = [
        e.features.descriptors[:: max(1, len(e.features) // per_entry)][:per_entry] for e in entries
    ]
    owner = np.concatenate([np.full(len(d), i, np.intp) for i, d in enumerate(picked)])
    return np.concatenate(picked), owner
