"""A live session as the web process holds it: identity, and a worker (a local process, or a Ray
actor) that does the work.

The transport and the REST routes talk to this object only; it forwards to the worker and turns
the worker's updates into the client's. Nothing here unpacks a frame: the worker decodes it, puts
it in order, counts it and measures its pose's ``server_total``.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any, Literal, Protocol, overload

from server.sessions.errors import SessionError
from server.sessions.processes.session_process import WorkerLost
from server.sessions.updates import PoseUpdate, SessionFailed
from server.sessions.web.viewers import Viewers


class SessionTakenOver:
    """The update a client gets when a newer connection to the same session, on another
    front-end of a shared cluster, took the session over (its socket ends with
    ``session_taken_over``); ``closed``: the session was closed or deleted there."""

    def __init__(self, message: str, closed: bool = False) -> None:
        self.message = message
        self.closed = closed


class SessionWorker(Protocol):
    """What a live session asks of its worker:
    ``server.sessions.processes.session_process.ProcessWorker``, or
    ``server.sessions.processes.ray_workers.RayWorker`` (the Ray actor's handle)."""

    dropped: int  # frames dropped before the worker saw them

    def call(self, method: str, *args: Any, timeout_s: float = 60.0) -> Any:
        """Run ``method`` on the session's host; its value (whatever that method returns)."""
        ...

    def post(self, method: str, *args: Any) -> None: ...

    def stop(self, save: bool, timeout_s: float = 120.0) -> dict: ...

    def kill(self) -> None: ...

    def describe(self) -> dict: ...


class LiveSession:
    """One live session in the web process, its work done by a ``SessionWorker``; ``on_lost``
    is told when the worker dies on its own, ``on_failed`` when the session fails in a live
    worker (its map is gone: ``Session.fail``) and must be stopped and saved."""

    def __init__(
        self,
        session_id: str,
        token_hash: str,
        created_at: float,
        start_worker: Callable[[LiveSession], SessionWorker],
        on_lost: Callable[[LiveSession, str], None] | None = None,
        on_failed: Callable[[LiveSession, str], None] | None = None,
    ) -> None:
        self.id = session_id
        self.token_hash = token_hash
        self.created_at = created_at
        self.closed = False
        self.final_meta: dict | None = None  # as saved by the worker's final snapshot
        self._stopping = False
        self._stopped = threading.Event()
        self.last_seen = time.monotonic()
        self.on_update: Callable[[object], None] | None = None
        self._on_lost = on_lost
        self._on_failed = on_failed
        self.sends_failed = 0  # connections ended because sending an update failed (web side)
        self.viewers = Viewers()  # read-only watchers (viewer links), fed by ``deliver``
        self.client_name = ""  # the latest hello's
        # The latest course message and when it came (monotonic): a shared room's race reads it.
        self.latest_course: tuple[float, dict] | None = None
        self.worker = start_worker(self)

    @property
    def last_seen(self) -> float:
        """When the client last said something (monotonic). A worker on a shared cluster also
        reports ``last_active``: the session is busy while any front-end feeds it."""
        remote = getattr(self.__dict__.get("worker"), "last_active", None)
        return self._last_seen if remote is None else max(self._last_seen, remote)

    @last_seen.setter
    def last_seen(self, value: float) -> None:
        self._last_seen = value

    # ------------------------------------------------------------------ from the worker
    def deliver(self, item) -> None:
        """An update from the worker (its reader thread): a pose gets the counts only this
        process knows (frames dropped before the worker saw them, sends that failed)."""
        if isinstance(item, PoseUpdate):
            item.dropped += self.worker.dropped
            item.failures["sends_failed"] = self.sends_failed
        elif isinstance(item, SessionTakenOver) and item.closed:
            self.closed = True  # ended by another front-end: the reaper lets go of it here
        elif isinstance(item, dict) and item.get("type") == "course":
            self.latest_course = (time.monotonic(), item)
        elif isinstance(item, SessionFailed):  # the worker lives on, to stop and save it
            self.closed = True
            if self._on_failed is not None:
                self._on_failed(self, item.message)
        self.viewers.deliver(item)
        self._tell(item)

    def _tell(self, item) -> None:
        on_update = self.on_update
        if on_update is not None:
            on_update(item)

    def lost(self, reason: str) -> None:
        """The worker died on its own: the client is told; the manager saves what is on disk."""
        self.closed = True
        self._tell(SessionFailed(reason))
        if self._on_lost is not None:
            self._on_lost(self, reason)

    # ------------------------------------------------------------------ from the client
    def configure(self, hello: dict) -> None:
        """The client's validated hello. Raises SessionError or ProtocolError."""
        if self.closed:
            raise SessionError("session_closed", "this session is closed; create a new one")
        self.worker.call("configure", hello)  # a new connection numbers its frames afresh
        self.client_name = str(hello.get("client_name", ""))
        self.last_seen = time.monotonic()

    def start(self, on_update: Callable[[object], None] | None) -> None:
        self.on_update = on_update

    def submit(self, data: bytes) -> None:
        """A frame message as it arrived, posted unread with its arrival time: the worker
        decodes and validates it, refuses it when its seq is out of order, counts it, and
        answers a frame it refuses with a FrameRefused update. Raises WorkerLost (a
        SessionError) when the worker is gone."""
        now = time.monotonic()
        self.last_seen = now
        self.worker.post("frame", data, now)

    def command(self, name: str, command_id: int, **fields) -> None:
        """A pilot command; raises CommandRefused."""
        self.worker.call("command", name, command_id, fields)

    def drain(self, timeout_s: float = 5.0) -> bool:
        return self.worker.call("drain", timeout_s, timeout_s=timeout_s + 5)

    # ------------------------------------------------------------------ REST
    def status(self) -> dict:
        try:
            status = self.worker.call("status")
        except WorkerLost:
            meta = self._saved_meta()
            if meta is None:
                raise
            return meta["status"]
        if self._stopping and not self._stopped.is_set():
            # The worker answers while its stop writes the final snapshot: the session is
            # closed (status.closed) once that has ended, saved or refused by the disk.
            status["closed"] = False
        # Frames dropped here before the worker saw them: received by the server all the same.
        status["frames_received"] += self.worker.dropped
        status["frames_dropped"] += self.worker.dropped
        status["failures"]["sends_failed"] = self.sends_failed
        threads = status.pop("threads")
        return status | {"worker": self.worker.describe() | {"threads": threads}}

    def _saved_meta(self) -> dict | None:
        """The final meta of a session being stopped and saved (a query that met its worker
        just gone waits for the stop to finish), else None."""
        if self._stopping:
            self._stopped.wait(30)
        return self.final_meta

    def download(self, name: str) -> bytes:
        """Raises WorkerLost when the worker ended meanwhile (``final_meta`` then says whether
        the session was saved: its files are on disk)."""
        return self.worker.call("download", name, timeout_s=300)

    # ------------------------------------------------------------------ the end
    @overload
    def stop(self, save: Literal[True] = True) -> dict: ...

    @overload
    def stop(self, save: bool) -> dict | None: ...

    def stop(self, save: bool = True) -> dict | None:
        """Stop the worker; with ``save``, after its final snapshot (returns the saved meta;
        raises SnapshotError when the save failed and the worker stays). Without, the worker
        is ended at once."""
        self.closed = True
        if not save:
            self.worker.kill()
            return None
        self._stopping = True
        try:
            self.final_meta = self.worker.stop(save=True)
        finally:
            self._stopping = False
            self._stopped.set()
        return self.final_meta
