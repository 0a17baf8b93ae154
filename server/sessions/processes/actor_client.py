"""What a front-end's handle on a session's Ray actor does besides calling Ray
(server/sessions/processes/ray_workers.py ``RayWorker`` is its Ray shell, which also polls the
actor's updates): it queues the ordered calls (the hello, frames, commands, the stop), the
newest frame winning, and submits them in order from one thread, numbered, at most
``MAX_FRAMES_IN_FLIGHT`` frames in flight; it hands the updates on to the live session, and
lets go of the session in each way it can end here (the actor died, another front-end ended
it, this one let go). No Ray import here: Ray stays in ray_workers.py (the actor handle given
is Ray's).
"""

from __future__ import annotations

import itertools
import logging
import threading
import time
from collections import deque
from concurrent.futures import Future
from multiprocessing import AuthenticationError

from server.sessions.processes.actor_stream import hang_up, open_stream
from server.sessions.processes.session_process import WorkerLost
from server.sessions.web.live import SessionTakenOver

log = logging.getLogger(__name__)

MAX_FRAMES_IN_FLIGHT = 2  # frame calls per session not yet run by the actor


class ActorClient:
    """A front-end's handle on one session actor, without the calls that need Ray
    (``RayWorker`` adds them): ``backend`` is the ``RayWorkers`` back-end (its ``owner``: this
    front-end, as the actors know it), ``actor`` Ray's handle on the actor, ``identity`` what
    its ``identity`` call answered; ``on_update`` and ``on_lost`` the live session's; ``owner``:
    this front-end owns the session (its updates come here)."""

    def __init__(
        self,
        backend,
        actor,
        session_id: str,
        identity: dict,
        on_update,
        on_lost,
        owner: bool,
    ) -> None:
        self.backend, self.actor, self.session_id = backend, actor, session_id
        self.info = identity["info"]
        self.data_dir = identity["data_dir"]
        self.on_update, self.on_lost = on_update, on_lost
        self.dropped = 0  # frames dropped here, before the actor saw them
        self.last_active = time.monotonic()
        self._owner = owner  # this front-end owns the session (its updates come here)
        self._cond = threading.Condition()
        self._queue: deque = deque()  # (method, args, Future | None), in order
        self._in_flight = 0  # frame calls submitted, not yet run
        self._numbers = itertools.count()
        self._lost: str | None = None  # why no more calls can go
        self._stopped = False  # this front-end stopped or killed it: its end is expected
        self._ended_elsewhere = False
        self._closing = False
        # Frames and updates past Ray (actor_stream.py); without it (it could not connect)
        # both go through Ray.
        self._stream = None
        address, authkey = identity["stream"]
        try:
            self._stream = open_stream(address, authkey, backend.owner)
        except (OSError, EOFError, AuthenticationError) as exc:
            log.warning("session %s: no stream to its actor (%s); all by Ray", session_id, exc)
        loops = [(self._send_loop, "ray-out"), (self._poll_loop, "ray-poll")]
        if self._stream is not None:
            loops.append((self._read_stream, "ray-in"))
        self._threads = [
            threading.Thread(target=target, name=f"{name}-{session_id}", daemon=True)
            for target, name in loops
        ]
        for thread in self._threads:
            thread.start()
        backend._workers.add(self)
        backend._with_threads.add(self)

    # ------------------------------------------------------------------ ordered calls
    def post(self, method: str, *args) -> None:
        """Queue without waiting for an answer (frames); raises WorkerLost when it is gone."""
        self._enqueue(method, args, None)

    def _enqueue(self, method: str, args: tuple, future: Future | None) -> None:
        with self._cond:
            if self._lost is not None:
                raise WorkerLost(self._lost)
            if method == "frame":
                for i, (queued, _, _) in enumerate(self._queue):
                    if queued == "frame":  # newest wins: the one waiting gives way
                        del self._queue[i]
                        self.dropped += 1
                        break
            self._queue.append((method, args, future))
            self._cond.notify_all()

    def _sendable(self) -> bool:
        return bool(self._queue) and (
            self._queue[0][0] != "frame" or self._in_flight < MAX_FRAMES_IN_FLIGHT
        )

    def _send_loop(self) -> None:
        """The one thread that submits ordered calls, numbered in queue order."""
        owner = self.backend.owner
        while True:
            with self._cond:
                while self._lost is None and not self._closing and not self._sendable():
                    self._cond.wait()
                if self._lost is not None or self._closing:
                    waiting, self._queue = list(self._queue), deque()
                    break
                method, args, future = self._queue.popleft()
                stream = self._stream if method == "frame" else None
                if method == "frame" and stream is None:  # a Ray call in flight until it ran
                    self._in_flight += 1
            number = next(self._numbers)
            if stream is not None:
                try:
                    stream.send((number, args))
                except (OSError, ValueError):  # the actor is gone: the poll says how
                    pass
                continue
            try:
                ref = self.actor.ordered.remote(owner, number, method, args)
            except Exception as exc:  # Ray shut down under us
                if future is not None:
                    future.set_exception(WorkerLost(f"the Ray connection failed: {exc}"))
                continue
            if future is not None:
                future.set_result(ref)
            if method == "frame":
                ref.future().add_done_callback(self._frame_done)
        reason = self._lost or "the front-end let go of the session"
        for _, _, future in waiting:
            if future is not None:
                future.set_exception(WorkerLost(reason))

    def _frame_done(self, _) -> None:
        with self._cond:
            self._in_flight -= 1
            self._cond.notify_all()

    def _poll_loop(self) -> None:
        """The ray-poll thread: long-polls the actor's updates (``RayWorker``'s, with Ray)."""
        raise NotImplementedError

    def _read_stream(self) -> None:
        """The ray-in thread: the updates the actor pushes on the stream, until it closes."""
        assert self._stream is not None
        while True:
            try:
                items = self._stream.recv()
            except (EOFError, OSError, TypeError):
                return
            for item in items:
                self._deliver(item)

    # ------------------------------------------------------------------ updates and ends
    def _deliver(self, item) -> None:
        try:
            self.on_update(item)
        except Exception:  # the listener's bug must not stop the updates
            log.exception("delivering a session update failed")

    def _let_go(self, reason: str) -> None:
        with self._cond:
            self._lost = self._lost or reason
            self._cond.notify_all()
        self.backend._workers.discard(self)
        if self._stream is not None:
            hang_up(self._stream)

    def _end(self, reason: str) -> None:
        """The actor died: on_lost once, unless this front-end ended it."""
        self._let_go(reason)
        on_lost = self.on_lost
        self.on_update = self.on_lost = _ignore
        if not self._stopped:
            on_lost(reason)

    def _end_elsewhere(self, reason: str) -> None:
        """Another front-end stopped or deleted the session: close it here without a word to
        the disk (the meta there is the other front-end's)."""
        self._ended_elsewhere = True
        self._let_go(reason)
        if not self._stopped:
            self._deliver(SessionTakenOver(reason, closed=True))
        self.on_update = self.on_lost = _ignore

    def _meta_on_disk(self) -> dict:
        from pathlib import Path

        from server.sessions.store import SessionStore, StoreError

        try:
            return SessionStore(Path(self.data_dir)).read_meta(self.session_id)
        except (StoreError, OSError):
            return {"id": self.session_id, "closed": False, "status": {}}

    def detach_threads(self) -> None:
        self._closing = True
        with self._cond:
            self._cond.notify_all()

    def join_threads(self, timeout_s: float) -> None:
        """Wait for the send and poll threads to end: a thread that touches Ray after
        ``ray.shutdown`` makes Ray's core worker end the whole process."""
        deadline = time.monotonic() + timeout_s
        for thread in self._threads:
            thread.join(max(0.0, deadline - time.monotonic()))


def _ignore(*_) -> None:
    pass
