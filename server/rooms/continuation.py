"""Continue in a saved room: relocalise the first frames by place recognition, then track in the
room's world frame and add the new keyframes to it.

Used by the offline ``track --room`` run and by a live session opened in a room, so that both
relocalise and extend a room the same way.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

from server.geometry import Intrinsics
from server.geometry.arrays import Float32Array, FloatArray, GreyImage
from server.registration import Tracker, TrackingState, TrackResult
from server.registration.config import RegistrationConfig
from server.registration.place import describe_place
from server.registration.preprocess import clean_depth, to_grey
from server.registration.verify import PlaceMatch, find_place
from server.rooms.room import Room, check_camera

log = logging.getLogger(__name__)


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
    """

    def __init__(self, room: Room, K: Intrinsics, cfg: RegistrationConfig | None = None) -> None:
        check_camera(room, K)
        self.room, self.K = room, K
        self.cfg = cfg or RegistrationConfig()
        self.database = room.database()
        self.map_keyframes = room.tracking_keyframes(self.cfg)
        self.tracker = Tracker(K, self.cfg)
        self.relocalisation: Relocalisation | None = None
        self.attempts = 0
        self._spent_ms = 0.0

    @property
    def relocalised(self) -> bool:
        return self.relocalisation is not None

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
        match = find_place(
            self.database, query, self.K, self.cfg.place, self.cfg.solver, self.cfg.depth
        )
        if match is None:
            self._spent_ms += (time.perf_counter() - t0) * 1e3
            return None
        T_guess = self.database.entry(match.keyframe_id).T_world_keyframe @ match.T_keyframe_query
        keyframe = next(k for k in self.map_keyframes if k.id == match.keyframe_id)
        self.tracker.resume_in_map(T_guess, keyframe, self.map_keyframes, self.database)
        # The tracker refines the guess against the keyframe's own corners: a second check too.
        result = self.tracker.track(colour, depth, T_device_camera, device_world)
        ms = (time.perf_counter() - t0) * 1e3
        self._spent_ms += ms
        if result.state is TrackingState.LOST:
            log.info("frame %d: place found (keyframe %d) but not tracked", index, keyframe.id)
            self.tracker = Tracker(self.K, self.cfg)
            return None
        self.relocalisation = Relocalisation(
            index, result.T_world_camera.copy(), match, self.attempts, ms, self._spent_ms
        )
        log.info(
            "relocalised at frame %d against keyframe %d (%d inliers) in %.0f ms",
            index,
            keyframe.id,
            match.inliers,
            ms,
        )
        return result

    def update_keyframe(self) -> bool:
        return self.tracker.update_keyframe() if self.relocalised else False
