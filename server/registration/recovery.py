"""The tracker's way back after flow loses a frame: the recent keyframes tried from the held
(or the device's) pose, then place recognition among every keyframe, in the map and in the map
segment being tracked; a segment merges into the map when it sees it again.

``Recovery`` owns what this needs across frames: the place database (``relocaliser``), the
archive of older keyframes, the segment being tracked, the frames lost in a row. It looks at the
tracker's keyframes, and calls the tracker's ``Anchor`` where it makes the frame a keyframe at a
pose of its own.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable
from dataclasses import replace

import numpy as np

from server.geometry import Intrinsics, invert, orthonormalize, pose_distance, rotation_angle_deg
from server.geometry.arrays import Float32Array, FloatArray, GreyImage
from server.registration.config import RegistrationConfig
from server.registration.frame_to_keyframe import Registration, Tracks, judge, track_keyframe
from server.registration.keyframe import Keyframe
from server.registration.keyframes import Keyframes
from server.registration.place import KeyframeDatabase, PlaceFeatures
from server.registration.relocalise import (
    Relocalisation,
    Relocaliser,
    align_to_surface,
    corrected,
)
from server.registration.results import Anchor, TrackingState, TrackResult

log = logging.getLogger(__name__)


class Recovery:
    """Relocalisation by place recognition, map segments and the keyframe archive, for the
    tracker that holds ``keyframes``: with the archive, every keyframe a place can be followed
    from by flow."""

    def __init__(self, K: Intrinsics, cfg: RegistrationConfig, keyframes: Keyframes) -> None:
        self.K, self.cfg, self.keyframes = K, cfg, keyframes
        self.relocaliser = Relocaliser(K, cfg)  # every keyframe's place features
        # The map segment being tracked (0: the map), how many were started, where the current
        # one started (frame index).
        self.segment = 0
        self.segments_started = 0
        self.segment_start = 0
        # The caller is behind (``Tracker.pace``): the segment looks for the map less often, and
        # a new keyframe is refined against fewer recent ones.
        self.behind = False
        # Frames lost in a row, and the motion before the loss (T_previous_last, 4x4), which
        # carries the last good pose over to a new segment.
        self.lost_run = 0
        self.velocity_before_loss: FloatArray = np.eye(4)
        self.archive: dict[int, Keyframe] = {}  # older keyframes by id, oldest first (archive)
        # The last frame's place features, with the grey image they describe (compared by
        # identity: frame indices may start again): a lost frame is looked up and may then
        # become a keyframe, which would describe it a second time (~8 ms of ORB).
        self._described: tuple[GreyImage, PlaceFeatures] | None = None

    def reset(self, places: KeyframeDatabase | None = None) -> None:
        """Forget every keyframe; ``places``: a saved map's place database to start from."""
        self.relocaliser = Relocaliser(self.K, self.cfg)
        self.archive.clear()
        for entry in places.entries if places is not None else []:
            self.relocaliser.add(entry.keyframe_id, 0, entry.T_world_keyframe, entry.features)
        self.segment = self.lost_run = 0

    def add_keyframe(self, kf: Keyframe, grey: GreyImage, depth: Float32Array) -> None:
        """Describe a new keyframe of the current segment for place recognition (its grey image
        and cleaned depth, metres)."""
        features = self.describe(grey, depth)
        self.relocaliser.add(kf.id, self.segment, kf.T_world_keyframe, features)

    def archive_keyframe(self, kf: Keyframe) -> None:
        """Keep a keyframe that leaves the recent ones for relocalisation: its image and corners
        (~0.4 MB at 640x480), not its surface (several MB); the oldest go past
        ``relocalise.archive_keyframes``."""
        self.archive[kf.id] = replace(kf, dense=None, depth=None)
        while len(self.archive) > self.cfg.relocalise.archive_keyframes:
            del self.archive[next(iter(self.archive))]

    def describe(self, grey: GreyImage, depth: Float32Array) -> PlaceFeatures:
        """A frame's place features (its grey image and cleaned depth, metres), described once
        however many steps of recovery and keyframing ask for them."""
        if self._described is None or self._described[0] is not grey:
            self._described = (grey, self.relocaliser.describe(grey, depth))
        return self._described[1]

    def merge_due(self, index: int) -> bool:
        """In a segment, frame ``index`` looks for the map (every ``relocalise.merge_every``,
        or ``merge_every_behind`` while the server is behind)."""
        r = self.cfg.relocalise
        every = r.merge_every_behind if self.behind else r.merge_every
        return self.segment != 0 and (index - self.segment_start) % every == 0

    def correct(self, keyframe_poses: dict[int, FloatArray], T_correction: FloatArray) -> None:
        """Move every keyframe (held, archived, in the place database) into a corrected world
        (``Tracker.apply_correction``): to its pose in ``keyframe_poses`` (4x4, metres, by id),
        else by ``T_correction`` (old world to new, 4x4)."""
        for kf in _unique([*self.keyframes.held(), *self.archive.values()]):
            kf.T_world_keyframe = corrected(
                kf.T_world_keyframe, keyframe_poses.get(kf.id), T_correction
            )
        self.relocaliser.correct(keyframe_poses, T_correction)

    def lose(self, velocity: FloatArray, first: bool) -> None:
        """One more frame lost; on the ``first`` of a run, ``velocity`` is the motion before it."""
        if first:
            self.velocity_before_loss = velocity
        self.lost_run += 1

    # ------------------------------------------------------------------ after a loss
    def retrack(
        self,
        grey: GreyImage,
        depth: Float32Array,
        T_world_pred: FloatArray,
        T_world_prior: FloatArray | None = None,
    ) -> Registration | None:
        """Flow after a loss: with a prior, its guess against the recent keyframes nearest to it
        first; then the held pose (T_world_pred) against the recent keyframes of this segment,
        newest first (only the current one when place recognition follows: it finds the others
        for less)."""
        K, cfg = self.K, self.cfg
        recent, current = self.keyframes.recent, self.keyframes.current
        if T_world_prior is not None:
            near = sorted(recent, key=lambda k: pose_distance(k.T_world_keyframe, T_world_prior))
            for kf in near:
                found = track_keyframe(kf, grey, depth, T_world_prior, K, cfg)
                if found is not None and judge(found.solution, cfg.state) is TrackingState.OK:
                    log.info("recovered against keyframe %d from the device pose", kf.id)
                    found.guess_from_prior = True
                    return found
        held = [k for k in reversed(recent) if k.segment == self.segment]
        if cfg.relocalise.enabled:
            held = [k for k in held if k is current]
        for kf in held:
            found = track_keyframe(kf, grey, depth, T_world_pred, K, cfg)
            if found is not None and judge(found.solution, cfg.state) is TrackingState.OK:
                log.info("recovered against keyframe %d", kf.id)
                return found
        return None

    def recover(
        self,
        grey: GreyImage,
        depth: Float32Array,
        tracks: Tracks | None,
        T_world_last: FloatArray,
    ) -> Registration | Relocalisation | None:
        """Place recognition for a frame flow could not register (relocalise config): the
        current keyframe, then the keyframes of the map (and of this segment) the database
        votes for; a verified place is the guess from which flow registers the frame: with the
        corners as last seen (``tracks``, just lost), else against that keyframe when it is held
        or archived. Returns that registration; the place alone when flow cannot follow this far
        (a wide baseline, or a keyframe no longer held: the tracker goes on from
        ``place_pose``); None when nothing verifies."""
        if not self.cfg.relocalise.enabled or len(self.relocaliser) == 0:
            return None
        query = self.describe(grey, depth)
        current = self.keyframes.current
        current_id = None if current is None else current.id
        place = self.relocaliser.find(query, T_world_last, {0, self.segment}, current_id)
        if place is None:
            return None
        segment = self.relocaliser.segment_of[place.keyframe_id]
        found = None
        if tracks is not None and current is not None and segment == self.segment:
            # Lost just now: the corners as last seen, searched for around the place's pose,
            # span less than a keyframe's corners would.
            found = track_keyframe(
                current, grey, depth, place.T_world_camera, self.K, self.cfg, tracks
            )
        if found is None or judge(found.solution, self.cfg.state) is TrackingState.LOST:
            found = self._track_place(place, grey, depth)
        if found is None or judge(found.solution, self.cfg.state) is TrackingState.LOST:
            log.debug("place found (keyframe %d), flow does not follow", place.keyframe_id)
            return place
        if segment != self.segment:
            log.info("back in the map from segment %d (not merged)", self.segment)
        self.segment = segment
        self.relocaliser.restart_sweep()
        log.info(
            "relocalised against keyframe %d (%d place inliers, %.0f ms)",
            place.keyframe_id,
            place.match.inliers,
            place.ms,
        )
        return found

    def restart_at_place(
        self, place: Relocalisation, depth: Float32Array, anchor: Anchor
    ) -> TrackResult | None:
        """A verified place that flow could not follow (``recover``): the frame (depth: cleaned,
        metres) becomes a keyframe at the place's pose (``place_pose``), WEAK. None when ICP
        disagrees with the place or the frame cannot anchor tracking."""
        segment = self.relocaliser.segment_of[place.keyframe_id]
        T_world_cur = self.place_pose(place, depth)
        if T_world_cur is None:
            return None
        result = anchor(T_world_cur, segment, relocalised=True)
        if result is None:
            return None
        self.relocaliser.restart_sweep()
        log.info(
            "frame %d: relocalised against keyframe %d by place (%d inliers); new keyframe",
            result.index,
            place.keyframe_id,
            place.match.inliers,
        )
        return result

    def start_segment(self, T_world_last: FloatArray, anchor: Anchor) -> TrackResult | None:
        """Nothing has registered for ``relocalise.reinit_after`` frames: the frame starts a new
        map segment, as its first keyframe, at the pose the motion before the loss carries the
        last good pose (T_world_last, 4x4, metres) to. Its frames are WEAK and not fused until it
        merges into the map (``merge``); the trajectory stays in one frame meanwhile. None when
        not due yet, or the frame cannot anchor tracking (too little texture or depth)."""
        frames = self.lost_run  # this one included
        if frames < self.cfg.relocalise.reinit_after or not self.cfg.relocalise.enabled:
            return None
        T_world_guess = orthonormalize(
            T_world_last @ np.linalg.matrix_power(self.velocity_before_loss, frames)
        )
        segment = self.segments_started + 1
        result = anchor(T_world_guess, segment)
        if result is None:
            return None
        self.segments_started, self.segment_start = segment, result.index
        log.info("frame %d: lost %d frames in a row; new segment %d", result.index, frames, segment)
        return result

    def place_pose(self, place: Relocalisation, depth: Float32Array) -> FloatArray | None:
        """T_world_camera (4x4, metres) of a verified place, refined by point-to-plane ICP
        (coarse, then at the tracker's own distance) against the matched keyframe's surface
        when that keyframe still holds one (the descriptor matches' pose as it is otherwise);
        None when fewer than ``relocalise.min_icp_overlap`` of the frame's points find it."""
        kf = self._held_keyframe(place.keyframe_id)
        surface = None if kf is None else kf.surface(self.K)
        if kf is None or surface is None:
            return place.T_world_camera
        T_kf_guess = invert(kf.T_world_keyframe) @ place.T_world_camera
        T, overlap = align_to_surface(T_kf_guess, surface, depth, self.K, self.cfg)
        if overlap < self.cfg.relocalise.min_icp_overlap:
            log.info("place of keyframe %d refused by ICP (overlap %.2f)", kf.id, overlap)
            return None
        return orthonormalize(kf.T_world_keyframe @ T)

    def merge(
        self,
        grey: GreyImage,
        depth: Float32Array,
        T_world_cur: FloatArray,
    ) -> tuple[int, FloatArray] | None:
        """Look this frame (tracked in a segment at ``T_world_cur``) up in the map; found (and
        confirmed by flow against a held map keyframe where there is one), the segment's
        keyframes move into the map with it. Returns (segment, T_correction: segment world to
        map world, 4x4) or None."""
        query = self.describe(grey, depth)
        place = self.relocaliser.find(query, T_world_cur, {0})
        if place is None:
            return None
        found = self._track_place(place, grey, depth)
        if found is not None and judge(found.solution, self.cfg.state) is not TrackingState.LOST:
            T_world_map = orthonormalize(found.kf.T_world_keyframe @ found.solution.T)
        else:
            place_pose = self.place_pose(place, depth)
            if place_pose is None:
                return None
            T_world_map = place_pose
        T_correction = orthonormalize(T_world_map @ invert(T_world_cur))
        segment = self.segment
        for kf in _unique([*self.keyframes.held(), *self.archive.values()]):
            if kf.segment == segment:
                kf.T_world_keyframe = orthonormalize(T_correction @ kf.T_world_keyframe)
                kf.segment = 0
        self.relocaliser.merge_segment(segment, T_correction)
        self.relocaliser.restart_sweep()
        self.segment = 0
        log.info(
            "segment %d merged into the map against keyframe %d (%.3f m, %.1f deg)",
            segment,
            place.keyframe_id,
            float(np.linalg.norm(T_correction[:3, 3])),
            rotation_angle_deg(T_correction),
        )
        return segment, T_correction

    def _track_place(
        self, place: Relocalisation, grey: GreyImage, depth: Float32Array
    ) -> Registration | None:
        """Flow from the place's keyframe, when still held, from the place's pose."""
        kf = self._held_keyframe(place.keyframe_id)
        if kf is None:
            return None
        return track_keyframe(kf, grey, depth, place.T_world_camera, self.K, self.cfg)

    def _held_keyframe(self, keyframe_id: int) -> Keyframe | None:
        """The keyframe with this id: a held one or one of the archive (the older keyframes,
        kept without their surface); None when it is no longer held."""
        for kf in self.keyframes.held():
            if kf.id == keyframe_id:
                return kf
        return self.archive.get(keyframe_id)


def _unique(keyframes: Iterable[Keyframe]) -> list[Keyframe]:
    """Each keyframe once (by identity), in order."""
    return list({id(k): k for k in keyframes}.values())
