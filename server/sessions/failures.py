"""A session's failures made visible: counted (the status and every pose carry the counts, so a
map that misses frames never looks healthy) and logged under the session's id, never its token.
"""

from __future__ import annotations

import logging
import sys
import threading
import time
from dataclasses import asdict, dataclass


@dataclass
class Failures:
    """What went wrong in one session so far; each is also logged. The pose's ``failures`` and
    the status's ``failures`` carry these names (shared/PROTOCOL.md)."""

    frames_failed: int = 0  # frames the server failed on: each answered internal_error
    fusions_failed: int = 0  # frames the map failed to fuse into the TSDF
    flight_map_failed: int = 0  # updates of the drone's occupancy map that failed
    flight_errors: int = 0  # flight steps (20 per second) that raised
    snapshots_failed: int = 0  # snapshots the disk refused (periodic and final)
    sends_failed: int = 0  # connections ended because sending them an update failed
    room_keyframes_failed: int = 0  # keyframes that could not be kept for the session's room
    loops_failed: int = 0  # keyframes the loop closer failed on, and map rebuilds that failed

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


class SessionLog(logging.LoggerAdapter):
    """A module's logger for one session: every message starts with ``session <id>:`` and its
    record carries ``session_id``. Tokens never reach it: a session knows only their hash."""

    def __init__(self, logger: logging.Logger, session_id: str) -> None:
        super().__init__(logger, {"session_id": session_id})

    def process(self, msg, kwargs):
        kwargs["extra"] = {**self.extra, **kwargs.get("extra", {})}
        return f"session {self.extra['session_id']}: {msg}", kwargs


class RateLimitedLog:
    """Logs the first of a run of repeated failures with its traceback, then at most one line
    per ``every_s`` that says how many more there were: a loop failing 20 times a second must
    not flood the log, yet none goes uncounted."""

    def __init__(self, log: logging.LoggerAdapter | logging.Logger, every_s: float = 10.0) -> None:
        self.log, self.every_s = log, every_s
        self._lock = threading.Lock()
        self._logged_at = -float("inf")
        self._unlogged = 0
        self._first = True

    def failure(self, what: str) -> None:
        """Call from an ``except`` block: ``what`` failed."""
        with self._lock:
            if self._first:
                self._first = False
                self._logged_at = time.monotonic()
                self.log.exception("%s failed", what)
                return
            self._unlogged += 1
            if time.monotonic() - self._logged_at < self.every_s:
                return
            unlogged, self._unlogged = self._unlogged, 0
            self._logged_at = time.monotonic()
        latest = sys.exc_info()[1]
        self.log.error(
            "%s failed %d more times in the last %.0f s (latest: %s: %s)",
            what,
            unlogged,
            self.every_s,
            type(latest).__name__,
            latest,
        )
