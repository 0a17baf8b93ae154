"""Continue in a saved room: relocalise the first frames by place recognition, then track in the
room's world frame and add the new keyframes to it.

Used by the offline ``track --room`` run and by a live session opened in a room, so that both
relocalise and extend a room the same way.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np

from server.geometry import Intrinsics, invert, rotation_angle_deg
from server.geometry.arrays import Float32Array, FloatArray, GreyImage
from server.registration import Tracker, TrackingState, TrackResult
from server.registration.config import RegistrationConfig
from server.registration.dense import build_dense_model, refine_dense, sample_dense_points
from server.registration.place import describe_place
from server.registration.preprocess import clean_depth, to_grey
from server.registration.sparse import NormalEquations
from server.registration.verify import PlaceMatch, find_place
from server.rooms.room import Room, check_camera, same_camera

log = logging.getLogger(__name__)

# Refining a place on the room's surface (another camera's frame, ``RoomTracker._refined``).
REFINE_MIN_MATCHES = 300  # projective point-to-plane matches at the last iteration
REFINE_MAX_MOVE_M = 0.15  # beyond, the place's own pose is kept
REFINE_MAX_TURN_DEG = 8.0


@dataclass
class Relocalisation:
    """Where a frame was found in the room."""

    frame: int  # index of the frame among those given to RoomTracker.track
    T_world_camera: FloatArray  # 4x4, metres, the room's world frame (after tracking it)
    match: PlaceMatch
    attempts: int  # frames tried, this one included
    ms: float  # time of this frame's place recognition and verification
    total_ms: float  # over all attempts


class RoomTracker:
    """A :class:`Tracker` that starts inside a saved room.

    ``track`` returns None for the frames before one is relocalised (no pose is known for them);
    from then on, the tracker's results, in the room's world frame. ``new_keyframes`` collects
    the keyframes made here, ready to be added to the room.

    ``other_camera``: a camera other than the room's may continue in it (a friend's phone
    joining a shared room): place recognition still finds its frames, as each side's features
    carry their own camera, but the room's keyframe images, seen by another lens at another
    size, are no keyframes to follow corners from. It tracks from keyframes of its own, the
    first at the pose the room gave (``same_camera`` False). Without it another camera raises
    RoomError (a run that adds its keyframes to the room, one camera per room file).
    """

    def __init__(
        self,
        room: Room,
        K: Intrinsics,
        cfg: RegistrationConfig | None = None,
        other_camera: bool = False,
    ) -> None:
        if not other_camera:
            check_camera(room, K)
        self.room, self.K = room, K
        self.cfg = cfg or RegistrationConfig()
        self.same_camera = same_camera(room, K)
        self.database = room.database()
        self.map_keyframes = room.tracking_keyframes(self.cfg) if self.same_camera else []
        self.tracker = Tracker(K, self.cfg)
        self.relocalisation: Relocalisation | None = None
        self.attempts = 0
        self._spent_ms = 0.0

    @property
    def relocalised(self) -> bool:
        return self.relocalisation is not None

    def pace(self, behind: bool) -> None:
        self.tracker.pace(behind)

    @property
    def lost(self) -> bool:
        """No pose for the latest frame: not found in the room yet, or tracking lost since."""
        return not self.relocalised or self.tracker.lost

    def track(
        self,
        colour: GreyImage,
        depth: Float32Array,
        T_device_camera: FloatArray | None = None,
        device_world: int = 0,
    ) -> TrackResult | None:
        """Register one frame (colour (H, W, 3) RGB uint8, depth (H, W) metres; the device's
        prior as Tracker.track takes it): None while the room has not recognised a frame yet,
        else the tracker's result (T_world_camera in the room's frame)."""
        if self.relocalised:
            return self.tracker.track(colour, depth, T_device_camera, device_world)
        index, self.attempts = self.attempts, self.attempts + 1
        t0 = time.perf_counter()
        grey, clean = to_grey(colour), clean_depth(depth, self.cfg.depth)
        query = describe_place(grey, clean, self.K, self.cfg.place, self.cfg.depth)
        # Its camera weighs both sides' points: another camera's keyframes (``other_camera``)
        # differ in focal length by tens of percent at most, a small change in the weights.
        match = find_place(
            self.database, query, self.K, self.cfg.place, self.cfg.solver, self.cfg.depth
        )
        if match is None:
            self._spent_ms += (time.perf_counter() - t0) * 1e3
            return None
        T_guess = self.database.entry(match.keyframe_id).T_world_keyframe @ match.T_keyframe_query
        if self.same_camera:
            # The tracker refines the guess against the keyframe's own corners: a second check.
            keyframe = next(k for k in self.map_keyframes if k.id == match.keyframe_id)
            self.tracker.resume_in_map(T_guess, keyframe, self.map_keyframes, self.database)
        else:  # its first keyframe where the room placed it, refined on the room's surface
            T_kq = self._refined(match.keyframe_id, match.T_keyframe_query, clean)
            T_guess = self.database.entry(match.keyframe_id).T_world_keyframe @ T_kq
            self.tracker = Tracker(self.K, self.cfg, T_world_first=T_guess)
        result = self.tracker.track(colour, depth, T_device_camera, device_world)
        ms = (time.perf_counter() - t0) * 1e3
        self._spent_ms += ms
        if result.state is TrackingState.LOST:
            log.info(
                "frame %d: place found (keyframe %d) but not tracked", index, match.keyframe_id
            )
            self.tracker = Tracker(self.K, self.cfg)
            return None
        self.relocalisation = Relocalisation(
            index, result.T_world_camera.copy(), match, self.attempts, ms, self._spent_ms
        )
        log.info(
            "relocalised at frame %d against keyframe %d (%d inliers) in %.0f ms",
            index,
            match.keyframe_id,
            match.inliers,
            ms,
        )
        return result

    def _refined(
        self, keyframe_id: int, T_keyframe_query: FloatArray, depth: Float32Array
    ) -> FloatArray:
        """The place's T_keyframe_query (ORB points alone: a few centimetres off) refined by
        projective point-to-plane ICP of this frame's depth (its camera) against the room
        keyframe's (the room's camera); the place's own pose when ICP finds too little to go
        on or moves it implausibly far (a wall alone lets it slide)."""
        kf = self.room.keyframe(keyframe_id)
        model = build_dense_model(clean_depth(kf.depth, self.cfg.depth), self.room.intrinsics)
        points, _ = sample_dense_points(depth, self.K, self.cfg.solver.dense_stride)
        none = NormalEquations(np.zeros((6, 6)), np.zeros(6))
        T, matches = refine_dense(
            T_keyframe_query, model, points, lambda _: none, self.cfg.solver, self.cfg.depth
        )
        moved = invert(T_keyframe_query) @ T
        if (
            matches < REFINE_MIN_MATCHES
            or np.linalg.norm(moved[:3, 3]) > REFINE_MAX_MOVE_M
            or rotation_angle_deg(moved) > REFINE_MAX_TURN_DEG
        ):
            return T_keyframe_query
        return T

    def update_keyframe(self) -> bool:
        return self.tracker.update_keyframe() if self.relocalised else False
