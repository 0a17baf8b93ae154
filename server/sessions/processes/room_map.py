"""One map for every phone in a shared room (server/sessions/web/shared_rooms.py): the room
owner's mapping process also listens on a local socket, and the worker of each phone that
joins fuses its frames into that map instead of a map of its own.

Each joined phone reads and fuses as a reader of its own (``JoinedMapper``): its map preview is what
its own frames show first, and its drone's occupancy updates cover every change fused since
its own last one, whoever fused it (``TSDFMap.occupancy_update``). The socket is an abstract
Unix socket (Linux: no file, no path length limit) with a random key per session, known only
to the web process and the workers it hands it to. The room's map outlives its owner's session
while phones that joined map into it: the process ends once the last of them has gone
(``RoomPhones``; the web process reaps it then: server/sessions/web/shared_rooms.py).
"""

from __future__ import annotations

import logging
import secrets
import threading
from dataclasses import dataclass
from multiprocessing import AuthenticationError
from multiprocessing.connection import Client, Listener
from typing import Any

import numpy as np

from server.sessions.processes.ipc import serve

# The owner's ``Mapper`` (mapper.py, which imports this module to listen): typed loosely here,
# so that the two modules do not import each other.
Mapper = Any


@dataclass(frozen=True)
class RoomAddress:
    """Where a room's map listens: an abstract Unix socket's name and its key."""

    address: str
    authkey: bytes

    @classmethod
    def new(cls, session_id: str) -> RoomAddress:
        return cls(f"\0dronesim-map-{session_id}-{secrets.token_hex(8)}", secrets.token_bytes(32))

    def connect(self):
        """A connection to the room's map (``MapperClient`` takes it as its pipe)."""
        return Client(self.address, family="AF_UNIX", authkey=self.authkey)


class JoinedMapper:
    """The room's ``Mapper`` as the worker of a phone that joined it uses it: the same calls,
    fused and read as reader ``name``. The room's map is live already (nothing to load) and its
    owner's session alone rebuilds it."""

    def __init__(self, mapper: Mapper, name: str) -> None:
        self.mapper = mapper
        self.name = name
        mapper.add_reader(name)

    def fuse(self, colour, depth, K, T_world_camera, occupancy=None, rebuild_pose=None) -> Any:
        return self.mapper.fuse(colour, depth, K, T_world_camera, occupancy, None, self.name)

    def occupancy(self, voxel_m: float, R_flight_world: np.ndarray):
        return self.mapper.occupancy(voxel_m, R_flight_world, self.name)

    def stats(self, wait: bool = True) -> dict | None:
        return self.mapper.stats(wait)

    def save(self, folder: str, periodic: bool = False) -> list[str]:
        return self.mapper.save(folder, periodic)

    def download(self, name: str) -> bytes:
        return self.mapper.download(name)

    def load(self, path: str) -> None:
        """Nothing: the phone joined the room's live map, which holds the room already."""

    def rebuild_start(self, *args) -> None:
        from server.mapping.tsdf import MapError  # Open3D: not in the web process

        raise MapError("the room's map is rebuilt by its owner's session only")

    rebuild_step = rebuild_finish = rebuild_cancel = rebuild_start

    def close(self) -> None:
        pass


class RoomPhones:
    """The joined phones a room's map serves (``serve_room``): ``wait`` until every one of
    them has gone. Its owner's session may end first: the map serves on until then."""

    def __init__(self) -> None:
        self._threads: list[threading.Thread] = []
        self._lock = threading.Lock()

    def add(self, thread: threading.Thread) -> None:
        with self._lock:
            self._threads.append(thread)

    def wait(self) -> None:
        while True:
            with self._lock:
                serving = [t for t in self._threads if t.is_alive()]
            if not serving:
                return
            for thread in serving:
                thread.join()


def serve_room(mapper: Mapper, room: RoomAddress, log: logging.LoggerAdapter) -> RoomPhones:
    """Listen at ``room`` (in a thread of the mapping process) and serve each phone that
    connects, as a reader of its own, until its connection closes."""
    listener = Listener(room.address, family="AF_UNIX", authkey=room.authkey)
    phones = RoomPhones()

    def accept() -> None:
        joined = 0
        while True:
            try:
                conn = listener.accept()
            except (AuthenticationError, EOFError, ConnectionError):  # not one of the room's
                log.warning("a connection to the room's map was refused")
                continue
            except OSError:  # the listener is closed: the process is ending
                return
            joined += 1
            view = JoinedMapper(mapper, f"phone-{joined}")
            thread = threading.Thread(
                target=serve, args=(view, conn, log), name=f"room-{joined}", daemon=True
            )
            phones.add(thread)
            thread.start()

    threading.Thread(target=accept, name="room-listener", daemon=True).start()
    return phones
