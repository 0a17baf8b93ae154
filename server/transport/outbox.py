"""What waits for one client's socket: the session's updates, in order, bounded.

A client that reads slowly (a phone on weak Wi-Fi, a viewer in a background tab) must not hold
the session back or make the server's memory grow, so a socket's updates wait in a bounded
queue and the oldest are dropped beyond it. Not every update can be lost, though: a pose or a
map chunk missed is made good by the next one, but a world corrected by a loop closure
(``MapCorrected``), the map preview's restart after it (a ``MapUpdate`` with ``reset``) and the
session's end (``SessionFailed``, ``SessionTakenOver``) change what every later message means.
Those are never dropped: the oldest update that may be lost goes instead.
"""

from __future__ import annotations

import asyncio
from collections import deque
from typing import Any

from server.sessions import MapCorrected, MapUpdate, SessionFailed, SessionTakenOver


def must_deliver(item: object) -> bool:
    """Updates the client's picture of the session is wrong without, not only late."""
    if isinstance(item, MapUpdate):  # the restart of the map, or the news that it has a surface
        return item.reset or (item.surface and len(item.points) == 0)
    return isinstance(item, MapCorrected | SessionFailed | SessionTakenOver)


class Outbox:
    """Updates waiting for one socket, in order, at most ``size`` (more only while every one
    waiting must be delivered). Of the types in ``latest_only`` only the newest waits, in the
    place of the first one queued (a 20 Hz drone state never crowds out the rest). Beyond
    ``size`` the oldest update that may be lost is dropped (``dropped`` counts them). Event-loop
    thread only."""

    def __init__(self, size: int, latest_only: tuple[type, ...] = ()) -> None:
        self.size = size
        self.latest_only = latest_only
        self.items: deque[Any] = deque()  # updates, or a latest_only type standing for its newest
        self.latest: dict[type, object] = {}
        self.dropped = 0
        self._ready = asyncio.Event()

    def put(self, item: object) -> None:
        slot = next((t for t in self.latest_only if isinstance(item, t)), None)
        if slot is not None:
            waiting = slot in self.latest
            self.latest[slot] = item
            if waiting:
                return
        if len(self.items) >= self.size:
            self._drop_oldest()
        self.items.append(item if slot is None else slot)
        self._ready.set()

    def _drop_oldest(self) -> None:
        for i, waiting in enumerate(self.items):
            if isinstance(waiting, type):
                del self.latest[waiting]
            elif must_deliver(waiting):
                continue
            del self.items[i]
            self.dropped += 1
            return

    async def get(self) -> Any:
        while not self.items:
            self._ready.clear()
            await self._ready.wait()
        item = self.items.popleft()
        if isinstance(item, type):
            item = self.latest.pop(item)
        return item

    def empty(self) -> bool:
        return not self.items

    def __len__(self) -> int:
        return len(self.items)
