"""A live session's map as the session's own threads use it beside the mapping thread: its
figures for a status, its files for a snapshot, its end. The map runs in a process of its own
(server/sessions/processes/mapper.py), or in a thread of this one (a Session made in-process,
as tests make them); once that process has ended (stopped, or died), the session answers with
what it last knew."""

from __future__ import annotations

from server.sessions.processes.mapper import Mapper, MapperClient, MapperLost
from server.sessions.runtime.counts import SessionCounts


class SessionMap:
    """The session's ``mapper`` for status queries, snapshots and the stop; the map's latest
    figures are kept in ``counts.map_stats``. ``closed``: the mapper has ended (no more calls
    go to it)."""

    def __init__(self, mapper: Mapper | MapperClient, counts: SessionCounts) -> None:
        self.mapper = mapper
        self.counts = counts
        self.closed = False

    def figures(self, wait: bool = False) -> dict:
        """The map's statistics: fresh when the mapper is idle; while it fuses, as of the latest
        fusion (a status never waits behind the mapper, which runs at a lower priority and may
        take seconds on a loaded machine). Once its process has ended, its last."""
        if not self.closed:
            try:
                fresh = self.mapper.stats(wait=wait or not self.counts.map_stats)
            except MapperLost:
                self.closed = True
            else:
                if fresh is not None:
                    self.counts.map_stats = fresh
        return self.counts.map_stats

    def save(self, staging: str, periodic: bool = False) -> list[str]:
        """The map's snapshot files written into ``staging`` (``Mapper.save``); their names
        (none once the mapper has ended: its files stay as the previous snapshot left them)."""
        if self.closed:
            return []
        try:
            return self.mapper.save(staging, periodic)
        except MapperLost:
            self.closed = True
            return []

    def close(self) -> None:
        """The session stops: its final figures, then the mapper lets go (its process ends)."""
        self.figures(wait=True)
        self.closed = True
        self.mapper.close()
