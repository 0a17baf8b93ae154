"""A live session's viewers: read-only links that watch the session without taking it over.

The session's owner hands out viewer tokens (``issue``); each is a 256-bit secret of which
only the SHA-256 is kept, checked in constant time as the session's own token is. A viewer's
socket listens (``listen``) and gets the session's poses, map preview points and drone states
and events as the owner's socket does (``deliver``, called with every update), plus, when it
joins, what came before it (``backlog``: the map preview so far and the latest pose and drone
state). Revoking a token ends its sockets (``revoke`` returns them to end). No web code here.
"""

from __future__ import annotations

import hmac
import secrets
import threading
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from server.sessions.errors import SessionError
from server.sessions.store import hash_token
from server.sessions.updates import (
    DroneNotice,
    DroneUpdate,
    MapCorrected,
    MapUpdate,
    PoseUpdate,
    RoomUpdate,
)
from server.simulation.drone_types import DroneEventKind

# What a viewer is shown; refused frames (the owner's errors) and failures are not for it.
VIEWED = (PoseUpdate, MapUpdate, MapCorrected, DroneUpdate, DroneNotice, RoomUpdate)
MAX_MAP_POINTS = 500_000  # preview points kept for viewers joining later (15 B each: 7.5 MB)


@dataclass
class ViewerSocket:
    """One viewer's connection as the session sees it: ``deliver`` takes an update (any
    thread: it must only queue), ``end(code, message)`` closes it (the web's event loop)."""

    viewer_id: str
    deliver: Callable[[object], None]
    end: Callable[[str, str], None]


class Viewers:
    """Viewer tokens and the sockets using them, for one live session; thread-safe."""

    def __init__(self, max_map_points: int = MAX_MAP_POINTS) -> None:
        self._tokens: dict[str, str] = {}  # viewer id -> token's sha256
        self._sockets: list[ViewerSocket] = []
        self._map: deque[MapUpdate] = deque()  # the preview so far, oldest first
        self._map_points = 0
        self.max_map_points = max_map_points
        self._latest_pose: PoseUpdate | None = None
        self._latest_drone: DroneUpdate | None = None
        self._spawned: DroneNotice | None = None
        self._lock = threading.Lock()

    # ------------------------------------------------------------------ tokens
    def issue(self, limit: int) -> tuple[str, str]:
        """A new viewer: (viewer id, token). Raises SessionError too_many_viewers when
        ``limit`` viewer tokens are out already."""
        with self._lock:
            if len(self._tokens) >= limit:
                raise SessionError(
                    "too_many_viewers",
                    f"this session has its maximum of {limit} viewer links; revoke one first",
                )
            viewer_id = secrets.token_hex(4)
            while viewer_id in self._tokens:
                viewer_id = secrets.token_hex(4)
            token = secrets.token_urlsafe(32)
            self._tokens[viewer_id] = hash_token(token)
        return viewer_id, token

    def check(self, token: str | None) -> str | None:
        """The viewer id ``token`` belongs to, or None. Every token is compared (in constant
        time), so the answer's timing says nothing about which tokens exist."""
        if not token:
            return None
        digest = hash_token(token)
        found = None
        with self._lock:
            for viewer_id, expected in self._tokens.items():
                if hmac.compare_digest(digest, expected):
                    found = viewer_id
        return found

    def ids(self) -> list[str]:
        with self._lock:
            return list(self._tokens)

    def revoke(self, viewer_id: str) -> list[ViewerSocket] | None:
        """Forget a viewer token; returns its open sockets (for the caller to end), or None
        when there is no such viewer."""
        with self._lock:
            if self._tokens.pop(viewer_id, None) is None:
                return None
            ending = [s for s in self._sockets if s.viewer_id == viewer_id]
            self._sockets = [s for s in self._sockets if s.viewer_id != viewer_id]
        return ending

    def revoke_all(self) -> list[ViewerSocket]:
        """The session ends: every token goes; returns the open sockets to end."""
        with self._lock:
            self._tokens.clear()
            ending, self._sockets = self._sockets, []
        return ending

    # ------------------------------------------------------------------ sockets
    def listen(self, socket: ViewerSocket) -> list[object]:
        """Add a viewer's socket; returns the backlog to send it first (in this order): the
        map preview so far, the drone's spawned event, the latest pose and drone state."""
        with self._lock:
            self._sockets.append(socket)
            backlog: list[object] = list(self._map)
            for item in (self._spawned, self._latest_pose, self._latest_drone):
                if item is not None:
                    backlog.append(item)
        return backlog

    def latest(self) -> tuple[PoseUpdate | None, DroneUpdate | None]:
        """The session's latest pose and drone state (a shared room shows them to the others:
        server/sessions/web/shared_rooms.py)."""
        with self._lock:
            return self._latest_pose, self._latest_drone

    def unlisten(self, socket: ViewerSocket) -> None:
        with self._lock:
            self._sockets = [s for s in self._sockets if s is not socket]

    def deliver(self, item: object) -> None:
        """An update of the session (the web process's reader thread): kept for later viewers
        where it matters, and handed to every viewer socket."""
        if not isinstance(item, VIEWED):
            return
        with self._lock:
            if isinstance(item, MapUpdate):
                self._keep_map(item)
            elif isinstance(item, PoseUpdate):
                self._latest_pose = item
            elif isinstance(item, DroneUpdate):
                self._latest_drone = item
            elif isinstance(item, DroneNotice) and item.event is DroneEventKind.SPAWNED:
                self._spawned = item
            sockets = list(self._sockets)
        for socket in sockets:
            socket.deliver(item)

    def _keep_map(self, update: MapUpdate) -> None:
        """The preview so far, at most max_map_points: beyond it the oldest points go (a
        viewer joining then misses those; the owner's own map is whole). A rebuilt map's
        preview (``reset``) starts the backlog afresh: the old points are of the old world."""
        if update.reset:
            self._map.clear()
            self._map_points = 0
        self._map.append(update)
        self._map_points += len(update.points)
        while self._map_points > self.max_map_points and len(self._map) > 1:
            self._map_points -= len(self._map.popleft().points)

    @property
    def map_points(self) -> int:
        return self._map_points


def merged_map(updates: list[MapUpdate]) -> MapUpdate | None:
    """Preview updates joined into one (for a viewer's backlog), or None when there are none."""
    if not updates:
        return None
    return MapUpdate(
        updates[-1].seq,
        np.concatenate([u.points for u in updates]),
        np.concatenate([u.colours for u in updates]),
        updates[-1].total_points,
        surface=updates[-1].surface,
    )
