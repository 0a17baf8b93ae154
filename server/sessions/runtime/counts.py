"""What the parts of one live session count, under the one lock a status reads them with."""

from __future__ import annotations

import threading

from server.registration import TrackingState, TrackResult
from server.sessions.failures import Failures


class SessionCounts:
    """The counts and flags the session's threads (tracking, mapping, loops, queries) share.
    ``lock`` guards every attribute; hold it for as short a time as possible (the tracking
    thread takes it for each pose)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.failures = Failures()  # flight_errors is the drone's own count
        self.dirty = False  # changed since the latest snapshot
        self.received = self.processed = self.dropped = 0
        self.last_seq_processed = -1
        self.fusion_skipped = 0
        # Tracked frames on their way into the map: from the pose until the mapping thread has
        # fused them (queued, or being fused), or they are known not to be fused.
        self.fusion_waiting = 0
        self.repeated = 0  # frames held at the pose before: a repeated colour or depth image
        self.states = {s.value: 0 for s in TrackingState}
        # Frames that carried the device's own pose, and those whose guess started from it.
        self.device_pose = {"frames": 0, "guesses": 0, "world_changes": 0}
        self.recovery = {
            "relocalised": 0,
            "segments": 0,
            "merged": 0,
            "in_segment": 0,
            "segment_frames_fused": 0,
        }
        self.map_stats: dict = {}  # the map's latest statistics (Mapper.stats)

    def failed(self, name: str) -> None:
        """Count one failure of the kind ``name`` (a field of Failures)."""
        with self.lock:
            setattr(self.failures, name, getattr(self.failures, name) + 1)

    def fusion_settled(self, frames: int = 1) -> None:
        """``frames`` counted in ``fusion_waiting`` are fused, failed to, or will not be."""
        with self.lock:
            self.fusion_waiting -= frames

    def changed(self) -> None:
        """Something a snapshot holds changed."""
        with self.lock:
            self.dirty = True

    def frame_figures(self) -> dict:
        """The status's counts of frames (call holding the lock)."""
        return {
            "frames_received": self.received,
            "frames_processed": self.processed,
            "frames_dropped": self.dropped,
            "fusion_skipped": self.fusion_skipped,
            "frames_repeated": self.repeated,
            "tracking_states": dict(self.states),
            "device_pose": dict(self.device_pose),
            "recovery": dict(self.recovery),
        }

    def count_recovery(self, result: TrackResult) -> None:
        """The status's ``recovery`` counts (call holding the lock)."""
        r = self.recovery
        r["relocalised"] += result.relocalised
        r["merged"] += result.merged is not None
        r["in_segment"] += result.recovery == "segment"
        r["segments"] = max(r["segments"], result.segment)  # numbered from 1 as they start
