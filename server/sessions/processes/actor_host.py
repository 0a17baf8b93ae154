"""What a session's Ray actor does (server/sessions/processes/ray_workers.py ``SessionActor`` is its
Ray shell): runs the session exactly as the web process runs a local one, in a ``ProcessWorker``
(server/sessions/processes/session_process.py: a worker process tracking and flying, a mapper
process fusing, a loop process when it closes loops), relays the ordered calls to it strictly by
each front-end's numbering, and pushes its updates to the owner's stream (actor_stream.py), or
keeps them for the owner's poll when it has none. No Ray here: Ray stays in ray_workers.py.

Why the session is not in the actor's own process: tracking there shared the GIL with Ray's
task loop and threads (which, among others, take it every 10 ms to check for signals), and
Open3D's integrate holds the GIL for its whole call. Measured on one node, 2 sessions x 15 fps:
tracking's p95 1.34-1.74x the process workers' with tracking in the actor (docs/SCALING.md).
The actor now only moves bytes, as the web process does for its local workers.

Its processes are the actor's children, started in a fresh interpreter (``fresh.FreshContext``:
a fork of the actor is unsafe, and multiprocessing's ``spawn`` and forkserver would run Ray's
worker script again in each), so they run on the actor's node; they end with it: when the actor
stops the session, when Ray ends the actor (Ray kills a worker's children as it exits) and when
the actor's process dies any other way (their pipes close with it). A worker or mapper that dies
fails the session as under the process workers: a dead mapper through the worker
(``MapperLost`` -> ``Session.fail`` -> ``SessionFailed``), a dead worker through the poll
(``lost``), the front-end then saving what is on disk and ending the actor.

A **shared room** has one map, as under the process workers (server/sessions/processes/
room_map.py): the mapper also listens for the room's phones at ``room_map`` (a ``NodeRoom``: an
abstract Unix socket, so on this node only, and the node's id, where the front-end places the
phones that join); the worker of a phone that joined starts no mapper and fuses into the room's.
Once a phone has joined (``room_shared``), the session's end leaves the mapper serving the
phones on: ``release`` ends the session without touching the mapper, and the actor stays, its
CPU reserved, until the mapper has ended after the last phone (``wait_for_map``, which reaps it:
no orphan) and then ends itself (ray_workers.py ``SessionActor.linger``)."""

from __future__ import annotations

import logging
import os
import threading
import time
from collections import deque
from dataclasses import dataclass

from server.sessions.errors import SessionError
from server.sessions.processes.actor_stream import StreamListener
from server.sessions.processes.fresh import FreshContext
from server.sessions.processes.ipc import attempt
from server.sessions.processes.room_map import RoomAddress
from server.sessions.processes.session_process import ProcessWorker, WorkerLost
from server.sessions.updates import PoseUpdate

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
    """Hosts one session in a ``ProcessWorker`` of its own. ``owner``: the id of the front-end
    that created it (the first owner, until another front-end sends a hello); ``node_id``: the
    Ray node it runs on (its room's map is reached there only)."""

    def __init__(self, args, owner: str, node_id: str = "", node_ip: str = "127.0.0.1") -> None:
        logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
        self._cond = threading.Condition()
        self._turn = threading.Lock()  # one ordered call at a time
        self._items: deque = deque()
        self._owner = owner
        self._next: dict[str, int] = {}  # front-end -> the number of its next ordered call
        self._ended: str | None = None
        self._lost: str | None = None  # why the session's worker died on its own
        self._last_active = time.monotonic()
        self.out_of_order = 0
        self.foreign_frames = 0  # frames from a front-end that was no longer the owner
        self.streamed_frames = 0  # frames that came by a stream, not by a Ray call
        self.skipped_updates = 0
        self.args = args
        # Its own map, which the phones joining its room reach at ``room_map`` too; or, for a
        # phone that joined a room, none: it fuses into the room's (on this node).
        room = NodeRoom.on(node_id, args.session_id) if args.room_map is None else None
        # Not holding the writers lock: a session outlives its front-end, and a restarted
        # front-end must not wait for it.
        self.worker = ProcessWorker(
            args,
            self._publish,
            self._worker_lost,
            context=FreshContext(),
            room_map=room,
            writers_lock=False,
        )
        self.room_map: NodeRoom | None = room
        self.info: dict = self.worker.describe() | {"actor_pid": os.getpid()}
        del self.info["kind"]  # the front-end's: ray
        # Frames in and updates out past Ray (actor_stream.py); the poll carries the rest.
        self.stream = StreamListener(node_ip, self._stream_frame, self._wake)
        threading.Thread(target=self._push, name="stream-out", daemon=True).start()

    @property
    def room_shared(self) -> bool:
        """Phones joined the room: the session's end leaves the mapper serving them."""
        return self.worker.room_shared

    def _worker_lost(self, reason: str) -> None:  # the worker's reader thread
        with self._cond:
            self._lost = reason
            self._ended = "failed"
            self._cond.notify_all()

    def _stream_frame(self, owner: str, number: int, args: tuple) -> None:
        with self._cond:  # a reader thread per front-end
            self.streamed_frames += 1
        self.ordered(owner, number, "frame", args)  # a frame is answered by updates

    def _wake(self) -> None:
        with self._cond:
            self._cond.notify_all()

    def _push(self) -> None:
        """The stream-out thread: the updates to the owner's stream, when it has one, in
        batches, in order; what a failed send leaves goes by the poll."""
        while True:
            with self._cond:
                while True:
                    if self._ended is not None and not self._items:
                        return
                    conn = self.stream.connection(self._owner) if self._items else None
                    if conn is not None:
                        break
                    self._cond.wait(1.0)
                owner, items = self._owner, list(self._items)
                self._items.clear()
            try:
                conn.send(items)
            except (OSError, ValueError):
                self.stream.forget(owner, conn)
                with self._cond:
                    if owner == self._owner:
                        self._items.extendleft(reversed(items))

    def _publish(self, item) -> None:  # the worker's reader thread
        if isinstance(item, PoseUpdate):  # poses come after the hello: self.worker is set
            item.dropped += self.worker.dropped  # frames dropped here, before the worker saw
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
            "stream": (self.stream.address, self.stream.authkey),
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
        if self._lost is not None:
            raise WorkerLost(self._lost)
        if self._ended is not None:
            raise SessionError("session_closed", "this session is closed; create a new one")
        if method == "configure":
            self.worker.call("configure", *args)
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
            return self.worker.post("frame", data, self._last_active)
        if method == "command":
            if owner != self._owner:
                raise SessionError(
                    "session_taken_over", "another connection took this session over"
                )
            return self.worker.call("command", *args)
        if method == "stop":
            # Its processes end (the mapper after the room's last phone, when it is shared).
            meta = self.worker.stop(*args)
            with self._cond:
                self._ended = "closed"
                self._cond.notify_all()
            return meta
        raise ValueError(f"not an ordered method: {method}")

    def query(self, method: str, args: tuple):
        """Status, meta, downloads, drain, snapshots: beside the ordered calls. ``share_map``:
        a phone joined the session's room (its map now serves past the session's end)."""
        if method == "share_map":
            self.worker.room_shared = True
            return True, None
        ok, value = attempt(self.worker, "call", (method, *args), log)
        if ok and method == "status":
            # Frames dropped here before the worker saw them: received by the session all the
            # same (as the web process counts its local workers').
            value["frames_received"] += self.worker.dropped
            value["frames_dropped"] += self.worker.dropped
            value = value | {
                "out_of_order_calls": self.out_of_order,
                "foreign_frames": self.foreign_frames,
                "streamed_frames": self.streamed_frames,
                "skipped_updates": self.skipped_updates,
            }
        return ok, value

    def updates(self, owner: str, timeout_s: float) -> dict:
        """Long-poll: the updates waiting for ``owner`` (none unless it is the owner, and none
        while its stream takes them), once there are any or after ``timeout_s``; with who owns
        the session, how long it has been idle and whether it ended."""
        deadline = time.monotonic() + timeout_s

        def polled() -> bool:
            return owner == self._owner and self.stream.connection(owner) is None

        with self._cond:
            while self._ended is None and not (self._items and polled()):
                wait = deadline - time.monotonic()
                if wait <= 0:
                    break
                self._cond.wait(wait)
            items = []
            if polled():
                items = list(self._items)
                self._items.clear()
            return {
                "items": items,
                "owner": owner == self._owner,
                "idle_s": time.monotonic() - self._last_active,
                "ended": self._ended,
                "lost": self._lost,
            }

    # ---- a shared room's map, past the session's end

    def release(self) -> bool:
        """End the session if it is still live (a delete: no save), its mapper left serving the
        room's phones; returns whether the mapper still runs (it ends after the last phone,
        ``wait_for_map``)."""
        with self._turn:
            if self._ended is None:
                try:
                    self.worker.stop(False)  # the mapper serves on (room_shared)
                except Exception:
                    log.exception("session %s: ending it failed", self.args.session_id)
                with self._cond:
                    self._ended = "closed"
                    self._cond.notify_all()
        mapper = self.worker.mapper_process
        return mapper is not None and mapper.is_alive()

    def wait_for_map(self) -> None:
        """Until the room's map has ended (after its last phone), and reap its process."""
        if self.worker.mapper_process is not None:
            self.worker.mapper_process.join()
