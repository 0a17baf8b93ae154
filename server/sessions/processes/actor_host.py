"""What a session's Ray actor does (server/sessions/processes/ray_workers.py ``SessionActor`` is its
Ray shell): hosts one SessionHost, runs the ordered calls strictly by each front-end's numbering,
and keeps the updates for the owner's long-poll. No Ray here: Ray stays in ray_workers.py.

The session's map is fused in a **mapper process** of the actor's own (``mapper_main``, the
process workers' mapper, at the same lower priority), not in a thread of the actor: Open3D's
integrate holds the GIL for its whole call, which beside tracking would stall it
(server/sessions/processes/mapper.py). The actor starts it as its child, so it runs on the
actor's node, and it ends with the actor: when the actor stops the session (its pipe closes),
when Ray ends the actor (Ray kills a worker's children as the worker exits) and when the actor's
process dies any other way (its end of the pipe closes with it; the mapper ends after the call
in hand). A mapper that dies fails the session as under the process workers (``MapperLost`` ->
``Session.fail`` -> ``SessionFailed``: the front-end then stops and saves it).

A **shared room** has one map, as under the process workers (server/sessions/processes/
room_map.py): the mapper also listens for the room's phones at ``room_map`` (a ``NodeRoom``: an
abstract Unix socket, so on this node only, and the node's id, where the front-end places the
phones that join); the actor of a phone that joined starts no mapper and fuses into the room's.
Once a phone has joined (``room_shared``), the session's end leaves the mapper serving the
phones on: ``release`` ends the session without touching the mapper, and the actor stays, its
CPU reserved, until the mapper has ended after the last phone (``wait_for_map``, which reaps it:
no orphan) and then ends itself (ray_workers.py ``SessionActor.linger``).

How it starts: a fresh interpreter (a fork of the actor, whose threads, Ray's among them, may
hold locks, is unsafe), by ``subprocess`` rather than multiprocessing's ``spawn``: ``spawn`` runs
the parent's ``__main__`` again in the child, here Ray's worker script, which would import Ray
into every mapper (measured: 224 against 194 MB resident, about a second more of CPU to start,
and a resource-tracker process beside it); and multiprocessing's exit handler joins its
children, which a mapper ignoring SIGTERM would hang. The pipe is the same
(``multiprocessing.Pipe``), its child's end passed down by descriptor."""

from __future__ import annotations

import logging
import multiprocessing
import os
import subprocess
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import TYPE_CHECKING

from server.sessions.errors import SessionError
from server.sessions.processes.ipc import attempt
from server.sessions.processes.room_map import RoomAddress

if TYPE_CHECKING:
    from server.sessions.processes.mapper import MapperClient

log = logging.getLogger(__name__)

_UPDATES_KEPT = 256  # updates waiting for the owner's poll; beyond, the oldest are skipped


@dataclass(frozen=True)
class NodeRoom(RoomAddress):
    """Where a room's map listens under Ray: its abstract Unix socket exists on one machine
    only, the Ray node ``node_id``, where every phone that joins the room must run."""

    node_id: str = ""

    @classmethod
    def on(cls, node_id: str, session_id: str) -> NodeRoom:
        room = RoomAddress.new(session_id)
        return cls(room.address, room.authkey, node_id)


class ActorHost:
    """Hosts one SessionHost. ``owner``: the id of the front-end that created it (the first
    owner, until another front-end sends a hello); ``node_id``: the Ray node it runs on (its
    room's map is reached there only)."""

    def __init__(self, args, owner: str, node_id: str = "") -> None:
        logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
        self._cond = threading.Condition()
        self._turn = threading.Lock()  # one ordered call at a time
        self._items: deque = deque()
        self._owner = owner
        self._next: dict[str, int] = {}  # front-end -> the number of its next ordered call
        self._ended: str | None = None
        self._last_active = time.monotonic()
        self.out_of_order = 0
        self.foreign_frames = 0  # frames from a front-end that was no longer the owner
        self.skipped_updates = 0
        self.args = args
        # Its own map, which the phones joining its room reach at ``room_map`` too; or, for a
        # phone that joined a room, none: it fuses into the room's (on this node).
        self.room_map: NodeRoom | None = None
        self.mapper_process: subprocess.Popen | None = None
        # Phones joined the room: the session's end leaves the mapper serving them (``release``).
        self.room_shared = False
        if args.room_map is None:
            self.room_map = NodeRoom.on(node_id, args.session_id)
            # First, so that its interpreter starts while this one imports the session's stack.
            self.mapper_process, mapper = start_mapper(args, self.room_map)
        else:
            from server.sessions.processes.mapper import MapperClient

            why = ": the room's map, which ended with the session of the phone that invited"
            mapper = MapperClient(args.room_map.connect(), why)
        try:
            from server.sessions.runtime.host import SessionHost

            self.host = SessionHost(args, self._publish, mapper)
            mapper.stats()  # up and answering (raises MapperLost when it died starting)
        except BaseException:
            mapper.close()
            if self.mapper_process is not None:
                end_mapper(self.mapper_process)
            raise
        pid = None if self.mapper_process is None else self.mapper_process.pid
        self.info: dict = self.host.describe() | {"mapper_pid": pid}

    def _publish(self, item) -> None:  # any of the session's threads
        with self._cond:
            self._items.append(item)
            if len(self._items) > _UPDATES_KEPT:
                self._items.popleft()
                self.skipped_updates += 1
            self._cond.notify_all()

    def identity(self) -> dict:
        return {
            "token_hash": self.args.token_hash,
            "created_at": self.args.created_at,
            "data_dir": self.args.data_dir,
            "info": self.info,
            "ended": self._ended,
            "room_map": self.room_map,
            "room_shared": self.room_shared,
        }

    def ordered(self, owner: str, number: int, method: str, args: tuple):
        """The hello, frames, commands and the stop: run strictly in each front-end's order.
        Answers as ``ipc.attempt`` does: (True, value) or (False, a RemoteError)."""
        with self._cond:
            deadline = time.monotonic() + 10.0
            while self._next.get(owner, 0) < number and (wait := deadline - time.monotonic()) > 0:
                self._cond.wait(wait)
            if self._next.get(owner, 0) != number:
                self.out_of_order += 1
        try:
            with self._turn:
                return attempt(self, "_run", (owner, method, args), log)
        finally:
            with self._cond:
                self._next[owner] = max(self._next.get(owner, 0), number + 1)
                self._cond.notify_all()

    def _run(self, owner: str, method: str, args: tuple):
        if self._ended is not None:
            raise SessionError("session_closed", "this session is closed; create a new one")
        if method == "configure":
            self.host.configure(*args)
            with self._cond:
                if owner != self._owner:  # taken over: the old owner's updates are not ours
                    self._owner = owner
                    self._items.clear()
                self._last_active = time.monotonic()
                self._cond.notify_all()  # the old owner's poll learns it at once
            return None
        if method == "frame":
            if owner != self._owner:
                self.foreign_frames += 1
                return None
            self._last_active = time.monotonic()
            # The front-end's arrival stamp is its own machine's monotonic clock, which means
            # nothing here when the actor runs on another node: the frame's arrival is its
            # arrival at the actor, so the pose's server_total leaves out the front-end's queue,
            # the hop to the actor and the updates' poll back.
            data, _front_end_arrival = args
            return self.host.frame(data, self._last_active)
        if method == "command":
            if owner != self._owner:
                raise SessionError(
                    "session_taken_over", "another connection took this session over"
                )
            return self.host.command(*args)
        if method == "stop":
            meta = self.host.stop(*args)  # the session's map closes: its process ends
            with self._cond:
                self._ended = "closed"
                self._cond.notify_all()
            if self.mapper_process is not None and not self.room_shared:
                end_mapper(self.mapper_process)
            return meta
        raise ValueError(f"not an ordered method: {method}")

    def query(self, method: str, args: tuple):
        """Status, meta, downloads, drain, snapshots: beside the ordered calls. ``share_map``:
        a phone joined the session's room (its map now serves past the session's end)."""
        if method == "share_map":
            self.room_shared = True
            return True, None
        ok, value = attempt(self.host, method, args, log)
        if ok and method == "status":
            value = value | {
                "out_of_order_calls": self.out_of_order,
                "foreign_frames": self.foreign_frames,
                "skipped_updates": self.skipped_updates,
            }
        return ok, value

    def updates(self, owner: str, timeout_s: float) -> dict:
        """Long-poll: the updates waiting for ``owner`` (none unless it is the owner), once there
        are any or after ``timeout_s``; with who owns the session and how long it has been idle."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while self._ended is None and not (owner == self._owner and self._items):
                wait = deadline - time.monotonic()
                if wait <= 0:
                    break
                self._cond.wait(wait)
            items = []
            if owner == self._owner:
                items = list(self._items)
                self._items.clear()
            return {
                "items": items,
                "owner": owner == self._owner,
                "idle_s": time.monotonic() - self._last_active,
                "ended": self._ended,
            }

    # ---- a shared room's map, past the session's end

    def release(self) -> bool:
        """End the session if it is still live (a delete: no save), its mapper left serving the
        room's phones; returns whether the mapper still runs (it ends after the last phone,
        ``wait_for_map``)."""
        with self._turn:
            if self._ended is None:
                try:
                    self.host.stop(False)  # its pipe to the mapper closes: the mapper serves on
                except Exception:
                    log.exception("session %s: ending it failed", self.args.session_id)
                with self._cond:
                    self._ended = "closed"
                    self._cond.notify_all()
        return self.mapper_process is not None and self.mapper_process.poll() is None

    def wait_for_map(self) -> None:
        """Until the room's map has ended (after its last phone), and reap its process."""
        if self.mapper_process is not None:
            self.mapper_process.wait()


# ---- the session's mapper process ----------------------------------------------------------------

# The mapper's command line: its end of the pipe by descriptor, then the session (for ``ps``).
_MAPPER_MAIN = (
    "import sys; from server.sessions.processes.actor_host import mapper_child; "
    "mapper_child(int(sys.argv[1]))"
)


def start_mapper(args, room: RoomAddress | None = None) -> tuple[subprocess.Popen, MapperClient]:
    """Start the session's mapper process, a child of this one (the process workers' mapper:
    ``mapper_main``, one Open3D thread, its priority lowered), listening for the room's phones
    at ``room`` when given; returns (the process, a ``MapperClient`` on it). It imports what
    this process can (its ``sys.path``)."""
    from server.sessions.processes.mapper import MapperClient

    here, there = multiprocessing.Pipe(duplex=True)
    try:
        process = subprocess.Popen(
            [
                sys.executable,
                "-c",
                _MAPPER_MAIN,
                str(there.fileno()),
                f"session-{args.session_id}-map",
            ],
            pass_fds=(there.fileno(),),
            stdin=subprocess.DEVNULL,
            env={**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p)},
        )
    finally:
        there.close()  # the child's now: its end of the pipe closes with it
    here.send((args.config.mapping, args.session_id, room))  # waits in the pipe for the child
    return process, MapperClient(here)


def mapper_child(fd: int) -> None:
    """The mapper process's start: the session's mapping configuration (and its room's
    address) from the pipe, then ``mapper_main`` until the pipe closes and, for a shared room,
    until its last phone has gone."""
    from multiprocessing.connection import Connection

    from server.sessions.processes.mapper import mapper_main

    conn = Connection(fd)
    config, session_id, room = conn.recv()
    mapper_main(conn, config, 1, session_id, room=room)


def end_mapper(process: subprocess.Popen, timeout_s: float = 10.0) -> None:
    """Wait for a mapper process whose pipe has closed to end (at once, or after the call in
    hand); kill it past ``timeout_s``."""
    try:
        process.wait(timeout_s)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait(timeout_s)
