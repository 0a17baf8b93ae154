"""What each reader of a map's changes has not read yet: the drones of the phones that share a
map (server/sessions/web/shared_rooms.py) each keep their own occupancy grid up to date from it
(``TSDFMap.occupancy_update``), and one drone's update must not take the changes from another.

Per reader: the TSDF blocks and the free-space blocks fused since its last update (packed keys,
``occupancy.pack_keys``), and how many of the map's cameras it has seen. A reader's first
update covers the whole map.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from server.geometry.arrays import Int64Array


@dataclass
class _Unread:
    blocks: Int64Array
    free_blocks: Int64Array
    cameras: int = 0  # cameras [0, this) were in an update already


class ChangeReaders:
    """The unread changes of every reader of one map (the caller holds the map's lock)."""

    def __init__(self) -> None:
        self._readers: dict[str, _Unread] = {}

    def fused(self, blocks: Int64Array) -> None:
        """TSDF blocks were fused: every reader has them to read."""
        for unread in self._readers.values():
            unread.blocks = np.union1d(unread.blocks, blocks)

    def carved(self, free_blocks: Int64Array) -> None:
        """Free-space blocks were carved: every reader has them to read."""
        if free_blocks.size:
            for unread in self._readers.values():
                unread.free_blocks = np.union1d(unread.free_blocks, free_blocks)

    def take(
        self,
        reader: str,
        cameras: int,
        all_blocks: Callable[[], Int64Array],
        all_free_blocks: Callable[[], Int64Array],
    ) -> tuple[Int64Array, Int64Array, int]:
        """``reader``'s unread (blocks, free blocks, first unread camera), now read; the whole
        map (``all_blocks()``, ``all_free_blocks()``, camera 0) for a reader new to it.
        cameras: how many the map has now."""
        unread = self._readers.get(reader)
        if unread is None:
            unread = _Unread(all_blocks(), all_free_blocks())
        self._readers[reader] = _Unread(np.empty(0, np.int64), np.empty(0, np.int64), cameras)
        return unread.blocks, unread.free_blocks, unread.cameras
