"""One frame's step, the same offline (``track``: server/pipeline.py) and live (a session's tracking
thread: server/sessions/runtime/tracking.py), so that both register, key and fuse frames alike.

1. ``prepare``: depth resampled to the camera's size, colour registered to depth.
2. ``track``: the pose (``Tracker.track``); the caller reports it at once.
3. ``settle``: the keyframe work ``track`` deferred (``update_keyframe``), then what the frame
   feeds: the map (every keyframe, every ``fuse_every``-th frame), the room and the loop closer
   (a new keyframe of the map), and a map segment's kept keyframes (fused once it merges).

No threads, queues or files here: the callers decide where each piece of work runs.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from server.geometry import Intrinsics
from server.geometry.arrays import Float32Array, FloatArray
from server.registration import Tracker, TrackingState, TrackResult
from server.registration.calibration import ColourToDepth
from server.registration.preprocess import resample_depth
from server.registration.relocalise import SegmentFrames
from server.rooms.continuation import RoomTracker


@dataclass
class Kept:
    """A keyframe of a map segment, kept for the map until the segment merges into it."""

    seq: int  # the caller's number of the frame (a dataset index, a client's seq)
    colour: np.ndarray  # registered to depth
    depth: Float32Array  # metres, the camera's size
    keyframe_id: int


@dataclass
class Settled:
    """What a frame feeds once its keyframe work is done."""

    new_keyframe: bool  # the frame became a keyframe
    fuse: bool  # it goes into the map, at its T_world_camera
    to_room: bool  # a new keyframe of the map (not of a segment): for the room and loop closer
    # A segment merged into the map with this frame: its kept keyframes, at their poses in the
    # map (T_world_camera, 4x4, metres).
    merged: list[tuple[Kept, FloatArray]] = field(default_factory=list)


class FrameStep:
    """Registers frames with ``tracker`` and says what each one feeds.

    colour_to_depth: resamples unregistered colour (a raw RGB-D sensor's) onto depth; None
    passes colour as it is. fuse_every: besides keyframes, the frames whose number (``settle``'s
    ``count``) is a multiple of it are fused. segment_keyframes_kept: the newest keyframes of a
    map segment kept for the map until it merges. fuse_first_placed: also fuse the first frame
    that is tracked (in a room: recognised in it), whatever its number (a live session's drone
    gets its first map with it)."""

    def __init__(
        self,
        tracker: Tracker | RoomTracker,
        intrinsics: Intrinsics,
        colour_to_depth: ColourToDepth | None,
        fuse_every: int,
        segment_keyframes_kept: int,
        fuse_first_placed: bool = False,
    ) -> None:
        self.tracker = tracker
        self.K = intrinsics
        self.colour_to_depth = colour_to_depth
        self.fuse_every = fuse_every
        self.fuse_first_placed = fuse_first_placed
        self.segment_frames: SegmentFrames[Kept] = SegmentFrames(segment_keyframes_kept)
        self.placed = False  # a frame has been tracked (in a room: recognised in it)

    def prepare(self, colour: np.ndarray, depth: Float32Array) -> tuple[np.ndarray, Float32Array]:
        """Colour (H, W, 3) and depth (metres) as the tracker takes them: depth resampled to
        the camera's size (nearest neighbour), colour registered to it. Shares nothing with
        ``track``: it may run ahead on another thread, in frame order."""
        depth = resample_depth(depth, self.K.width, self.K.height)
        if self.colour_to_depth is not None:
            colour = self.colour_to_depth(colour, depth)
        return colour, depth

    def pace(self, behind: bool) -> None:
        """The caller is behind (``TrackerMemory.pace``), or no longer."""
        self.tracker.pace(behind)

    def track(
        self,
        colour: np.ndarray,
        depth: Float32Array,
        T_device_camera: FloatArray | None = None,
        device_world: int = 0,
    ) -> TrackResult | None:
        """The prepared frame's pose (``Tracker.track``); None in a room before a frame was
        recognised in it. Its keyframe work waits for ``settle``."""
        return self.tracker.track(
            colour, depth, T_device_camera=T_device_camera, device_world=device_world
        )

    def settle(
        self, result: TrackResult, seq: int, count: int, colour: np.ndarray, depth: Float32Array
    ) -> Settled:
        """After the pose went out: the keyframe work (``result`` is updated in place), and
        what the frame feeds. seq: the frame's number for the caller; count: its number in the
        stream (from 0), for ``fuse_every``."""
        self.tracker.update_keyframe()  # a switch to an earlier keyframe, or a new one
        new_keyframe = result.new_keyframe
        tracked = result.state is not TrackingState.LOST
        first_placed = self.fuse_first_placed and tracked and not self.placed
        self.placed = self.placed or tracked
        settled = Settled(
            new_keyframe=new_keyframe,
            fuse=result.fusable and (new_keyframe or first_placed or count % self.fuse_every == 0),
            # A segment's keyframes stay out of the room and the pose graph: their poses are in
            # the segment's world, a guess of where it lies (Tracker: segments).
            to_room=new_keyframe and result.segment == 0,
        )
        if result.recovery == "segment" and new_keyframe:
            kept = Kept(seq, colour, depth, result.keyframe_id)
            self.segment_frames.keep(result.segment, kept, result.T_world_camera)
        elif result.merged is not None:
            settled.merged = self.segment_frames.merged(*result.merged)
        return settled
