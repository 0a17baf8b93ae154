"""Recovery after a loss: where a frame lies among every keyframe of the tracker's map.

Optical flow needs a pose guess near the truth; after a gap in the frames or a fast sweep it has
none. Place recognition does not: each keyframe is described once (ORB with depth,
:mod:`server.registration.place`) and a lost frame is matched against them, the current
keyframe first (the usual case: the camera moved on further than flow reaches), then the
keyframes the database votes for, each verified geometrically
(:mod:`server.registration.verify`). The caller refines the verified pose with flow.

A map may have segments: after a loss that nothing recovered, the tracker starts a new one from
the current frame (ORB-SLAM3's Atlas keeps such maps apart the same way). Look-ups can be limited
to some segments, so that a segment finds its way back into the main map; merging moves a
segment's keyframes here with it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from typing import Generic, TypeVar

import numpy as np

from server.geometry import Intrinsics, orthonormalize, pose_distance
from server.geometry.arrays import Float32Array, FloatArray, GreyImage
from server.registration.config import RegistrationConfig
from server.registration.dense import DenseModel, refine_dense, sample_dense_points
from server.registration.place import KeyframeDatabase, PlaceFeatures, describe_place
from server.registration.sparse import NormalEquations
from server.registration.verify import PlaceMatch, verify_place

Item = TypeVar("Item")


@dataclass
class Relocalisation:
    """A frame found in the map: against keyframe ``keyframe_id``, at ``T_world_camera`` (4x4,
    metres, from the descriptor matches alone: the tracker refines it)."""

    keyframe_id: int
    T_world_camera: FloatArray
    match: PlaceMatch
    ms: float  # the look-up's time: the vote and the verifications


def align_to_surface(
    T_keyframe_camera: FloatArray,
    surface: DenseModel,
    depth: Float32Array,
    K: Intrinsics,
    cfg: RegistrationConfig,
) -> tuple[FloatArray, float]:
    """Point-to-plane ICP of a frame's depth (H, W, metres, cleaned) onto a keyframe's surface
    from the guess T_keyframe_camera (4x4, metres): at twice the tracker's matching distance,
    then at its own. A place's pose from descriptor matches is good to a few centimetres; the
    surface takes it to the tracker's accuracy. Returns the refined T_keyframe_camera and the
    share of the frame's sampled points that found the surface at the end (0 when none)."""
    points, _ = sample_dense_points(depth, K, cfg.solver.dense_stride)
    if len(points) == 0:
        return T_keyframe_camera, 0.0

    def no_sparse(_: FloatArray) -> NormalEquations:
        return NormalEquations(np.zeros((6, 6)), np.zeros(6))

    T, matches = T_keyframe_camera, 0
    for reach in (2.0, 1.0):
        solver = replace(
            cfg.solver,
            dense_max_distance_m=reach * cfg.solver.dense_max_distance_m,
            dense_iterations=2 * cfg.solver.dense_iterations,
        )
        T, matches = refine_dense(T, surface, points, no_sparse, solver, cfg.depth)
    return T, matches / len(points)


def corrected(
    T_world_keyframe: FloatArray, T_known: FloatArray | None, T_correction: FloatArray
) -> FloatArray:
    """A keyframe's pose after a correction: the pose graph's own (``T_known``) where it has
    one, else the old pose moved by T_correction (4x4, metres)."""
    T = T_correction @ T_world_keyframe if T_known is None else np.asarray(T_known, np.float64)
    return orthonormalize(T)


class SegmentFrames(Generic[Item]):
    """What a caller that fuses (a live session, ``track``) keeps of a map segment's keyframes
    until the segment merges: an item (images, ...) and its pose in the segment's world each;
    the newest ``limit`` of one segment. A new segment drops what an abandoned one kept."""

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self.segment = 0
        self.kept: list[tuple[Item, FloatArray]] = []

    def keep(self, segment: int, item: Item, T_world_camera: FloatArray) -> None:
        if segment != self.segment:
            self.segment, self.kept = segment, []
        self.kept = [*self.kept, (item, T_world_camera)][-self.limit :]

    def merged(self, segment: int, T_correction: FloatArray) -> list[tuple[Item, FloatArray]]:
        """The items of ``segment``, which merged into the map, with their poses moved by
        T_correction (segment world to map world, 4x4); [] when another segment was kept."""
        kept = self.kept if segment == self.segment else []
        self.segment, self.kept = 0, []
        return [(item, T_correction @ T) for item, T in kept]


class Relocaliser:
    """The place database of a tracker's keyframes, and the look-up of a lost frame in it."""

    def __init__(self, K: Intrinsics, cfg: RegistrationConfig) -> None:
        self.K = K
        self.cfg = cfg
        r = cfg.relocalise
        self.place = replace(
            cfg.place,
            orb_features=r.orb_features,
            vote_features=r.vote_features,
            candidates=r.candidates,
            ransac_iterations=r.ransac_iterations,
        )
        self.database = KeyframeDatabase()
        self.segment_of: dict[int, int] = {}  # keyframe id -> map segment
        self._sweep = 0  # where the next vote starts in the keyframes ordered by distance

    def __len__(self) -> int:
        return len(self.database)

    def describe(self, grey: GreyImage, depth: Float32Array) -> PlaceFeatures:
        """Place features of a frame: grey (H, W) uint8, depth (H, W) metres, cleaned."""
        return describe_place(grey, depth, self.K, self.place, self.cfg.depth)

    def add(
        self, keyframe_id: int, segment: int, T_world_keyframe: FloatArray, features: PlaceFeatures
    ) -> None:
        """A keyframe of ``segment`` at T_world_keyframe (4x4, metres) with its features."""
        self.database.add(keyframe_id, T_world_keyframe, features)
        self.segment_of[keyframe_id] = segment

    def merge_segment(self, segment: int, T_correction: FloatArray) -> None:
        """Merge ``segment`` into the map: its keyframes move by ``T_correction`` (4x4, segment
        world to map world, T_new = T_correction @ T_old) and belong to segment 0 from now on."""
        for e in self.database.entries:
            if self.segment_of[e.keyframe_id] == segment:
                e.T_world_keyframe = T_correction @ e.T_world_keyframe
                self.segment_of[e.keyframe_id] = 0

    def correct(self, keyframe_poses: dict[int, FloatArray], T_correction: FloatArray) -> None:
        """Keyframes moved (loop closure): those in ``keyframe_poses`` to their corrected
        T_world_keyframe, every other one by ``T_correction`` (4x4, metres, T_new = T @ T_old)."""
        for e in self.database.entries:
            e.T_world_keyframe = corrected(
                e.T_world_keyframe, keyframe_poses.get(e.keyframe_id), T_correction
            )

    def restart_sweep(self) -> None:
        """The next look-up votes from the keyframes nearest its pose again (after a recovery)."""
        self._sweep = 0

    def find(
        self,
        query: PlaceFeatures,
        T_world_near: FloatArray,
        segments: set[int],
        first: int | None = None,
    ) -> Relocalisation | None:
        """The best verified keyframe of ``segments`` for ``query``, or None.

        ``first``: a keyframe id verified before the vote (the current keyframe). The vote covers
        ``relocalise.vote_keyframes`` keyframes, nearest ``T_world_near`` (4x4, metres: the last
        good pose) first; each call that finds nothing moves on to the next ones. At most
        ``relocalise.candidates`` keyframes are verified, ``first`` included.
        """
        t0 = time.perf_counter()
        allowed = [
            e for e in self.database.entries if self.segment_of.get(e.keyframe_id) in segments
        ]
        if not allowed or len(query) == 0:
            return None
        tried: list[int] = []
        best: PlaceMatch | None = None
        if first is not None and any(e.keyframe_id == first for e in allowed):
            tried.append(first)
            best = self._verify(first, query)
        if best is None:
            allowed.sort(key=lambda e: pose_distance(e.T_world_keyframe, T_world_near))
            n = self.cfg.relocalise.vote_keyframes
            start = self._sweep if self._sweep < len(allowed) else 0
            window = {e.keyframe_id for e in allowed[start : start + n]}
            self._sweep = start + n
            for kf_id, votes in self.database.candidates(query, self.place, window):
                if kf_id in tried:
                    continue
                if len(tried) >= self.place.candidates:
                    break
                tried.append(kf_id)
                found = self._verify(kf_id, query)
                if found is not None and (best is None or found.inliers > best.inliers):
                    found.votes = votes
                    best = found
        if best is None:
            return None
        T_world_kf = self.database.entry(best.keyframe_id).T_world_keyframe
        return Relocalisation(
            best.keyframe_id,
            T_world_kf @ best.T_keyframe_query,
            best,
            (time.perf_counter() - t0) * 1e3,
        )

    def _verify(self, keyframe_id: int, query: PlaceFeatures) -> PlaceMatch | None:
        features = self.database.entry(keyframe_id).features
        c = self.cfg
        return verify_place(features, query, self.K, self.place, c.solver, c.depth, keyframe_id)
