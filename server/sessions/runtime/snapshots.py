"""A live session's snapshots: its files (map, trajectory, the flight in progress) and meta,
written whole or not at all, periodically from the mapping thread and once when it stops."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path

from server.mapping.tsdf import MapError
from server.sessions.errors import SnapshotError
from server.sessions.runtime.counts import SessionCounts
from server.sessions.store import SessionStore


class Snapshots:
    """write(staging, periodic): puts the session's files into a staging folder, returns their
    names (``periodic``: the mapping thread's, not one asked for or the last); meta: the
    session's meta, written with them. ``error`` says why the latest snapshot failed (None:
    it did not)."""

    def __init__(
        self,
        store: SessionStore,
        session_id: str,
        counts: SessionCounts,
        interval_s: float,
        log: logging.LoggerAdapter,
        write: Callable[[Path, bool], list[str]],
        meta: Callable[[], dict],
    ) -> None:
        self.store = store
        self.session_id = session_id
        self.counts = counts
        self.interval_s = interval_s
        self.log = log
        self.write = write
        self.meta = meta
        self.error: str | None = None
        self._last = time.monotonic()
        # The mapping thread's periodic snapshot and one asked for (REST, a room shared with a
        # joining phone) share one staging folder: one at a time.
        self._lock = threading.Lock()

    def take(self, periodic: bool = False) -> None:
        """Write the files and the meta as one snapshot: staged beside the previous one, then
        renamed into place (``SessionStore.commit``), so a crash leaves a whole snapshot.

        Raises SnapshotError when the disk refuses (full, gone): the previous snapshot stays
        whole, everything stays in memory, and ``error`` says why until a later snapshot
        succeeds."""
        with self._lock:
            self._take(periodic)

    def _take(self, periodic: bool) -> None:
        with self.counts.lock:
            self.counts.dirty = False
        try:
            names = self.write(self.store.staging(self.session_id), periodic)
            self.error = None
            self.store.commit(self.session_id, names, self.meta())
        except (OSError, MapError) as exc:  # MapError: Open3D refused to write
            with self.counts.lock:
                self.counts.dirty = True
                self.counts.failures.snapshots_failed += 1
            self.error = f"{type(exc).__name__}: {exc}"
            raise SnapshotError(f"session {self.session_id}: snapshot failed ({exc})") from exc
        finally:
            self._last = time.monotonic()  # a failed one is retried after the interval

    def take_if_due(self) -> None:
        """The periodic snapshot, when something changed; a failure keeps everything in
        memory."""
        with self.counts.lock:
            dirty = self.counts.dirty
        if not dirty or time.monotonic() - self._last < self.interval_s:
            return
        try:
            self.take(periodic=True)
        except SnapshotError as exc:
            self.log.error("%s; the previous one stays whole and the map stays in memory", exc)
