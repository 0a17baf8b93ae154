"""A live session's tracking thread: takes the newest frame from a one-frame inbox, runs the frame
step (server/frame_step.py), publishes the pose at once, then hands the frame's fusion to the
mapping thread (server/sessions/runtime/fusion.py). Between two frames it moves the tracker into
each corrected world a loop closure made.

Frames arrive faster than they can be processed on a busy server; for a live camera the inbox
holds one frame and the newest wins, so latency stays bounded and stale frames are dropped and
counted. A recording's connection (hello ``recorded``) queues as many as it may have in flight
(``protocol.queued_frames``): a replay that waits for room loses none.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable

import numpy as np

from server.evaluation.trajectory import Trajectory
from server.frame_step import FrameStep
from server.geometry import Intrinsics
from server.mapping.frame_input import at_depth_size
from server.registration import Tracker, TrackingState, TrackResult
from server.rooms.continuation import RoomTracker
from server.sessions.config import SessionConfig
from server.sessions.errors import SessionError
from server.sessions.runtime.counts import SessionCounts
from server.sessions.runtime.flight import Flight
from server.sessions.runtime.fusion import FuseJob, SessionFusion
from server.sessions.runtime.loop_closing import Correction
from server.sessions.updates import FrameData, MapCorrected, PoseUpdate, Update

# After a frame dropped for a newer one, this many frames count as behind (about 1 s at 15 fps).
BEHIND_FRAMES = 15


def live_step(tracker: Tracker | RoomTracker, K: Intrinsics, config: SessionConfig) -> FrameStep:
    """The frame step of a live session's tracking thread (``SessionTracking``)."""
    return FrameStep(
        tracker,
        K,
        None,  # a live client's colour is registered to its depth (the phone's is)
        config.mapping.fuse_every,
        config.registration.relocalise.segment_keyframes_kept,
        # With the first frame placed in a room the drone's map is fed the room's map (a fresh
        # session's first frame is its first keyframe anyway).
        fuse_first_placed=True,
    )


class SessionTracking:
    """The tracking thread (``start``) of one session: ``submit`` hands in frames, ``correct``
    a loop closure's correction. frame_failed: answers a frame the step failed on (logged,
    counted); failure_counts: the session's failures, for every pose."""

    def __init__(
        self,
        step: FrameStep,
        fusion: SessionFusion,
        counts: SessionCounts,
        publish: Callable[[Update], None],
        log: logging.LoggerAdapter,
        name: str,
        flight: Flight | None,
        frame_failed: Callable[[int, Exception], None],
        failure_counts: Callable[[], dict[str, int]],
    ) -> None:
        self.step = step
        self.fusion = fusion
        self.counts = counts
        self.publish = publish
        self.log = log
        self.flight = flight
        self.frame_failed = frame_failed
        self.failure_counts = failure_counts
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        # Under counts.lock: the poses so far (timestamp, T_world_camera), the last seq accepted.
        self._trajectory: list[tuple[float, np.ndarray]] = []
        self._last_seq = -1
        self._wake = threading.Condition()  # guards the inbox, _busy, _stopping, _corrections
        self._inbox: deque[FrameData] = deque()  # oldest first
        self._queued = 1  # frames the inbox keeps (this connection's queued_frames)
        self._busy = False  # the thread holds a frame
        self._stopping = False
        self._corrections: list[Correction] = []
        self._world = 0  # the corrected world the tracker is in (tracking thread)
        self._device_world = 0  # the last frame's device_world (tracking thread)
        # Tracking thread: the frames dropped when it last looked, and how many frames more count
        # as behind (``FrameStep.pace``).
        self._dropped_seen = 0
        self._behind_left = 0

    # ------------------------------------------------------------------ other threads'
    def start(self) -> None:
        self._thread.start()

    @property
    def started(self) -> bool:
        return self._thread.ident is not None

    def renumber(self, queued: int = 1) -> None:
        """A new connection numbers its frames afresh (a reloaded page); ``queued``: how many of
        its frames the inbox keeps (1: the newest wins)."""
        with self.counts.lock:
            self._last_seq = -1
        with self._wake:
            self._queued = max(1, int(queued))

    def accept(self, seq: int) -> None:
        """Frame ``seq`` arrived (before its images are decoded): counted as received, or
        refused (SessionError bad_sequence) unless it is above the connection's last seq."""
        with self.counts.lock:
            if seq <= self._last_seq:
                raise SessionError(
                    "bad_sequence",
                    f"sequence number {seq} is not above the last one ({self._last_seq})",
                )
            self._last_seq = seq
            self.counts.received += 1

    def submit(self, frame: FrameData) -> None:
        """Queue a frame (``accept``-ed); when the inbox is full, the oldest frame waiting is
        dropped in its favour."""
        with self._wake:
            while len(self._inbox) >= self._queued:
                self._inbox.popleft()
                with self.counts.lock:
                    self.counts.dropped += 1
            self._inbox.append(frame)
            self._wake.notify()

    def correct(self, correction: Correction) -> None:
        """A verified loop corrected the world (loop thread): taken between two frames."""
        with self._wake:
            self._corrections.append(correction)
            self._wake.notify()

    def drain(self, timeout_s: float) -> bool:
        """Wait until every submitted frame has been processed (or dropped); False on timeout."""
        deadline = time.monotonic() + timeout_s
        with self._wake:
            while self._inbox or self._busy:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return False
                self._wake.wait(remaining)
        return True

    def stop(self) -> None:
        """End the thread after the frame in hand (``join`` waits for it)."""
        with self._wake:
            self._stopping = True
            self._wake.notify()

    def join(self, timeout_s: float) -> None:
        if self.started:
            self._thread.join(timeout=timeout_s)

    def trajectory(self) -> Trajectory:
        with self.counts.lock:
            stamps = np.array([t for t, _ in self._trajectory], dtype=np.float64)
            poses = np.array([T for _, T in self._trajectory]).reshape(-1, 4, 4)
        return Trajectory(stamps, poses)

    def pose_count(self) -> int:
        with self.counts.lock:
            return len(self._trajectory)

    # ------------------------------------------------------------------ the tracking thread
    def _run(self) -> None:
        while True:
            with self._wake:
                while not self._inbox and not self._stopping and not self._corrections:
                    self._wake.wait()
                frame = self._inbox.popleft() if self._inbox else None
                corrections, self._corrections = self._corrections, []
                self._busy = frame is not None
                stopping = self._stopping
            if corrections:  # between two frames: track never sees a half-corrected world
                self._apply_corrections(corrections)
            if frame is not None:
                try:
                    self._process(frame)
                except Exception as exc:  # one bad frame must not end the session's worker
                    self.frame_failed(frame.seq, exc)
                with self._wake:
                    self._busy = False
                    self._wake.notify_all()  # for drain()
            if stopping and frame is None:
                return

    def _apply_corrections(self, corrections: list[Correction]) -> None:
        """Move the tracker into each corrected world in turn and tell the client
        (map_corrected): poses already sent stay as they were; those of frames from
        ``from_seq`` on are in the corrected world."""
        tracker = self.step.tracker
        for c in corrections:
            if isinstance(tracker, Tracker):  # loops never run in a room (RoomTracker)
                try:
                    tracker.apply_correction(c.keyframes, c.T_correction)
                except Exception:
                    self.log.exception("correcting the tracker failed")
                    self.counts.failed("loops_failed")
                    continue
            self._world = c.world
            if self.flight is not None:  # the drone is shown in the corrected world at once
                self.flight.world_corrected(c.T_correction)
            with self.counts.lock:
                from_seq = self.counts.last_seq_processed + 1
            keyframes = [(i, c.seqs[i], T) for i, T in sorted(c.keyframes.items())]
            self.publish(MapCorrected(c.loops, from_seq, c.T_correction, keyframes, c.refused))

    def _pace(self) -> None:
        """A frame dropped for a newer one makes the next BEHIND_FRAMES frames count as behind:
        the tracker then spends less on look-ups that may wait (``FrameStep.pace``)."""
        with self.counts.lock:
            dropped = self.counts.dropped
        if dropped > self._dropped_seen:
            self._behind_left = BEHIND_FRAMES
        elif self._behind_left > 0:
            self._behind_left -= 1
        self._dropped_seen = dropped
        self.step.pace(self._behind_left > 0)

    def _process(self, frame: FrameData) -> None:
        """Track the frame and publish its pose at once; then the keyframe work the tracker
        deferred (a new keyframe, or a switch to an earlier one), and the frame's fusion job:
        the client never waits for either."""
        t0, cpu0 = time.perf_counter(), time.thread_time()
        self._pace()
        colour, depth = self.step.prepare(frame.colour, frame.depth)
        result = self.step.track(
            colour, depth, T_device_camera=frame.T_device_camera, device_world=frame.device_world
        )
        if result is None:  # in a room, before a frame is recognised in it: no pose yet
            result = _not_placed(frame.seq)
        timings = {
            "decode": frame.decode_ms,
            **{f"track_{k}": v for k, v in result.timings_ms.items()},
        }
        # This thread's own CPU time: track minus track_cpu is time spent waiting for a core
        # (or the GIL), which tells a busy machine from slow registration. Read inside the wall
        # interval, so that it never exceeds it.
        timings["track_cpu"] = (time.thread_time() - cpu0) * 1e3
        timings["track"] = (time.perf_counter() - t0) * 1e3
        tracked = result.state is not TrackingState.LOST
        if self.flight is not None and tracked:  # before the pose: a tap may name this frame
            self.flight.camera_moved(frame.seq, result.T_world_camera, depth)
        counts = self.counts
        with counts.lock:
            self._trajectory.append((frame.timestamp, result.T_world_camera))
            counts.last_seq_processed = frame.seq
            counts.processed += 1
            counts.states[result.state.value] += 1
            counts.repeated += result.repeated is not None
            counts.device_pose["frames"] += frame.T_device_camera is not None
            counts.device_pose["guesses"] += result.prior_used
            counts.device_pose["world_changes"] += frame.device_world != self._device_world
            self._device_world = frame.device_world
            counts.count_recovery(result)
            counts.fusion_waiting += 1  # until its fusion is done or known not to come
            dropped, processed = counts.dropped, counts.processed
            counts.dirty = True
        # The one place server_total is measured: from the frame's arrival (FrameData.received_at)
        # to its pose, published now.
        timings["server_total"] = (time.monotonic() - frame.received_at) * 1e3
        self.publish(
            PoseUpdate(
                frame.seq,
                frame.timestamp,
                result.T_world_camera,
                result.state,
                result.inliers,
                result.new_keyframe or result.keyframe_due,
                timings,
                dropped,
                processed,
                self.failure_counts(),
                result.recovery,
            )
        )
        queued = False  # the frame's fusion job: the mapping thread then counts it off
        try:
            settled = self.step.settle(result, frame.seq, processed - 1, colour, depth)
            if settled.merged:  # a merged segment's keyframes, fused between the live frames
                self.fusion.add_merged(
                    [
                        FuseJob(k.seq, k.colour, k.depth, T, False, world=self._world)
                        for k, T in settled.merged
                    ]
                )
            if settled.fuse:
                # A keyframe goes to the room and the loop closer as tracked; a plain frame only
                # to the map, which fuses at the depth's own size (a phone's is 1/16 of its
                # colour's): sent so, it crosses to the mapping process in a fraction.
                fused_colour, fused_depth = (
                    (colour, depth)
                    if settled.new_keyframe
                    else (at_depth_size(colour, frame.depth), frame.depth)
                )
                queued = self.fusion.queue(
                    FuseJob(
                        frame.seq,
                        fused_colour,
                        fused_depth,
                        result.T_world_camera,
                        settled.new_keyframe,
                        result.keyframe_id,
                        self._world,
                    )
                )
        finally:
            if not queued:
                counts.fusion_settled()


def _not_placed(seq: int) -> TrackResult:
    """The answer for a frame of a session in a room before any frame was recognised in it:
    lost, at the identity (no pose is known yet)."""
    return TrackResult(seq, np.eye(4), TrackingState.LOST, 0, np.inf, 0.0, -1, False)
