"""Session worker processes: each live session's tracking, mapping and flight run in a process
of its own, apart from the web process.

Why processes: the web process's event loop then only moves bytes; a session's native crash
(OpenCV, Open3D) ends that session alone; and each process's thread pools are sized for its
share of the cores. Processes come from a forkserver that has already imported the numerical
stack, so starting one takes tens of milliseconds, not the seconds of a fresh interpreter.

The two sides talk over one duplex pipe, in the shape of ``ipc`` (the worker runs ``ipc.serve``):
- web -> worker: ``(call_id, method, args)``; call_id None for a message that wants no answer
  (frames, which arrive at camera rate and are answered by poses);
- worker -> web: ``("reply", call_id, ok, value)`` and ``("update", item)``.
Frames, the hello, commands, drain and stop are handled in arrival order on the worker's main
thread (a drain after a bye must come after its frames); slow queries (status, downloads,
snapshot) run beside it so that they never hold up a frame.
"""

from __future__ import annotations

import atexit
import itertools
import logging
import multiprocessing
import os
import queue
import signal
import threading
import weakref
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future
from concurrent.futures import TimeoutError as FutureTimeout

from server.sessions.errors import SessionError
from server.sessions.processes.room_map import RoomAddress

log = logging.getLogger(__name__)

_INLINE = {"configure", "frame", "command", "drain", "stop"}  # in order, on the main thread
# Imported once in the forkserver, shared by every worker and mapper it forks.
_PRELOAD = [
    "server.sessions.runtime.host",
    "server.sessions.processes.mapper",
    "server.sessions.processes.loop_process",
]


class WorkerLost(SessionError):
    """The session's worker is gone (crashed, killed, or stopped)."""

    def __init__(self, message: str) -> None:
        super().__init__("session_failed", message)


# ---- the worker's side ------------------------------------------------------------------------


def _worker_main(conn, args, mapper_conn, loops_conn=None, writers_lock: bool = True) -> None:
    """Entry point of a worker process: host the session (its map in the mapping process at
    the other end of ``mapper_conn``, its loop closer in the loop process at the other end of
    ``loops_conn`` when it closes loops) and serve the pipe until told to stop or until the web
    process goes away. ``writers_lock``: hold the data dir's writers lock while it lives."""
    from server.sessions.processes.ipc import as_remote, prepare_child, reply, serve
    from server.sessions.store import hold_writers_lock

    # The web process stops each session with a final save, which must find its worker alive.
    prepare_child()
    if writers_lock:  # a restarted server cleans only after this process ends
        hold_writers_lock(args.data_dir)
    from server.sessions.failures import SessionLog
    from server.sessions.processes.mapper import MapperClient
    from server.sessions.runtime.host import SessionHost

    # Everything the worker says goes through one queue and one thread, in order: a reply (to
    # a drain, say) never overtakes the poses published before it.
    outgoing: queue.SimpleQueue = queue.SimpleQueue()

    def forward() -> None:
        while (message := outgoing.get()) is not None:
            try:
                conn.send(message)
            except (OSError, ValueError):
                return

    sender = threading.Thread(target=forward, name="outgoing", daemon=True)
    sender.start()
    try:
        # A dead mapper fails the session, which then ends cleanly: stopped and saved by the
        # web side (Session.fail), this process serving it to the end. A phone that joined a
        # room fuses into the room's map, in its owner's mapping process.
        why_lost = ""
        if args.room_map is not None:
            mapper_conn = args.room_map.connect()
            why_lost = ": the room's map, which ended with the session of the phone that invited"
        mapper = MapperClient(mapper_conn, why_lost)
        host = SessionHost(args, lambda item: outgoing.put(("update", item)), mapper, loops_conn)
    except Exception as exc:
        outgoing.put(reply(0, False, as_remote(exc)))
        outgoing.put(None)
        sender.join()
        return
    outgoing.put(reply(0, True, host.describe()))
    session_log = SessionLog(log, args.session_id)
    if not serve(
        host, conn, session_log, send=outgoing.put, ordered=_INLINE, beside=2, last="stop"
    ):
        # The web process is gone (killed): its snapshots on disk are whole; end at once, so
        # that a restarted server does not find this process still writing beside it.
        os._exit(0)
    outgoing.put(None)
    sender.join()


# ---- the web process's side -------------------------------------------------------------------


class ProcessWorker:
    """The web process's handle on one session's worker process (and its mapper process, and
    its loop process when the session closes loops online).

    ``call`` blocks until the worker answers (run it off the event loop); ``post`` only queues:
    a writer thread sends, so a worker busy with a command never blocks the caller. Frames
    waiting beyond ``max_waiting_frames`` (a stalled worker) are dropped, oldest first, and
    counted in ``dropped``. Updates arrive on a reader thread and go to ``on_update``; when the
    process ends without having been stopped, every waiting call fails with WorkerLost and
    ``on_lost`` is called once with the reason."""

    kind = "process"

    def __init__(
        self,
        args,
        on_update: Callable[[object], None],
        on_lost: Callable[[str], None],
        start_timeout_s: float = 60.0,
        max_waiting_frames: int = 4,
        context=None,
        room_map: RoomAddress | None = None,
        writers_lock: bool = True,
    ) -> None:
        """context: where its processes come from (default the forkserver; a Ray actor's
        ``fresh.FreshContext``); room_map: where the phones joining its room reach its map
        (default a new address); writers_lock: its processes hold the data dir's writers lock
        (``store.hold_writers_lock``), so that a restarted server waits for them (not a Ray
        actor's: those outlive the front-end by design)."""
        from server.sessions.processes.loop_process import loops_main
        from server.sessions.processes.mapper import mapper_main

        ctx = _context() if context is None else context
        self._conn, child = ctx.Pipe(duplex=True)
        # Its own map (which phones joining its room reach at ``room_map`` too), or, for a
        # phone that joined a room, none: it fuses into the room's.
        self.room_map: RoomAddress | None = None
        # Phones joined the room and may still map into it: the mapper is not waited for or
        # killed when this session ends (``keep_room_map``), it ends after them.
        self.room_shared = False
        self.mapper_process = None
        to_mapper = mapper_end = None
        if args.room_map is None:
            self.room_map = room_map or RoomAddress.new(args.session_id)
            to_mapper, mapper_end = ctx.Pipe(duplex=True)
        # The loop closer apart from tracking too: in the worker it would share the tracker's GIL
        # (server/sessions/processes/loop_process.py). Siblings, as a worker (a daemon) may not
        # fork.
        self.loops_process = None
        to_loops = loops_end = None
        if args.config.closes_loops(in_room=args.room_dir is not None):
            to_loops, loops_end = ctx.Pipe(duplex=True)
            self.loops_process = ctx.Process(
                target=loops_main,
                daemon=True,
                name=f"session-{args.session_id}-loops",
                args=(loops_end, args.session_id),
            )
        # Tracking and mapping in two processes: Open3D's fusion holds the GIL for its whole
        # call, which in one process would stall tracking (server/sessions/processes/mapper.py).
        if mapper_end is not None:
            self.mapper_process = ctx.Process(
                target=mapper_main,
                daemon=True,
                name=f"session-{args.session_id}-map",
                args=(
                    mapper_end,
                    args.config.mapping,
                    1,
                    args.session_id,
                    args.data_dir if writers_lock else None,
                    self.room_map,
                ),
            )
        self.process = ctx.Process(
            target=_worker_main,
            args=(child, args, to_mapper, to_loops, writers_lock),
            daemon=True,
            name=f"session-{args.session_id}",
        )
        self.on_update, self.on_lost = on_update, on_lost
        started: Future = Future()
        self._calls: dict[int, Future] = {0: started}  # 0: the host's start-up
        self._ids = itertools.count(1)
        self._lock = threading.Lock()  # sending, and the table of calls
        self._stopped = False  # the worker was told to stop: its end is expected
        self._lost: str | None = None
        self._outgoing: deque = deque()  # messages for the writer thread, in order
        self._waiting_frames = 0
        self.max_waiting_frames = max_waiting_frames
        self.dropped = 0  # frames dropped here, before the worker saw them
        self._wake = threading.Condition(self._lock)
        if self.mapper_process is not None:
            self.mapper_process.start()
        if self.loops_process is not None:
            self.loops_process.start()
        self.process.start()
        _RUNNING.add(self)
        for end in (child, to_mapper, mapper_end, to_loops, loops_end):  # theirs now
            if end is not None:
                end.close()
        self._reader = threading.Thread(
            target=self._read, name=f"worker-{args.session_id}", daemon=True
        )
        self._reader.start()
        threading.Thread(
            target=self._write, name=f"worker-out-{args.session_id}", daemon=True
        ).start()
        self.info = self._wait(started, start_timeout_s, "start")

    def describe(self) -> dict:
        loops = self.loops_process
        return {
            "kind": self.kind,
            **self.info,
            "mapper_pid": None if self.mapper_process is None else self.mapper_process.pid,
            "loops_pid": None if loops is None else loops.pid,
        }

    # ------------------------------------------------------------------ calls
    def post(self, method: str, *args) -> None:
        """Queue without waiting for an answer; raises WorkerLost when the worker is gone."""
        self._send((None, method, args))

    def call(self, method: str, *args, timeout_s: float = 60.0):
        """Run ``method`` on the session's host and return its value (or raise its error)."""
        future: Future = Future()
        with self._lock:
            call_id = next(self._ids)
            self._calls[call_id] = future
        try:
            self._send((call_id, method, args))
        except WorkerLost:
            with self._lock:
                self._calls.pop(call_id, None)
            raise
        return self._wait(future, timeout_s, method, call_id)

    def _wait(self, future: Future, timeout_s: float, method: str, call_id: int = 0):
        from server.sessions.processes.ipc import result

        try:
            ok, value = future.result(timeout_s)
        except FutureTimeout:
            with self._lock:
                self._calls.pop(call_id, None)
            raise WorkerLost(
                f"the session's worker did not answer {method} within {timeout_s:.0f} s"
            ) from None
        return result(ok, value)

    def _send(self, message) -> None:
        with self._wake:
            if self._lost is not None:
                raise WorkerLost(self._lost)
            if message[1] == "frame":
                if self._waiting_frames >= self.max_waiting_frames:
                    self._drop_oldest_frame()
                self._waiting_frames += 1
            self._outgoing.append(message)
            self._wake.notify()

    def _drop_oldest_frame(self) -> None:
        for i, (_, method, _) in enumerate(self._outgoing):
            if method == "frame":
                del self._outgoing[i]
                self._waiting_frames -= 1
                self.dropped += 1
                return

    def _write(self) -> None:
        """The writer thread: sends queued messages in order until the worker is gone."""
        while True:
            with self._wake:
                while not self._outgoing and self._lost is None:
                    self._wake.wait()
                if self._lost is not None:
                    return
                message = self._outgoing.popleft()
                if message[1] == "frame":
                    self._waiting_frames -= 1
            try:
                self._conn.send(message)
            except (OSError, ValueError, TypeError):
                # The reader sees the end and reports it. TypeError: close() on another thread
                # emptied the connection's handle mid-send (seen once in CI, a killed mapper).
                return

    # ------------------------------------------------------------------ the reader thread
    def _read(self) -> None:
        while True:
            try:
                message = self._conn.recv()
            except (EOFError, OSError):
                break
            if message[0] == "update":
                try:
                    self.on_update(message[1])
                except Exception:  # the listener's bug must not stop the answers
                    log.exception("delivering a session update failed")
                continue
            _, call_id, ok, value = message
            with self._lock:
                future = self._calls.pop(call_id, None)
            if future is not None:
                future.set_result((ok, value))
        self.process.join(timeout=5)
        code = self.process.exitcode
        if not self._stopped:
            self._end_helpers()
        reason = (
            "the session's worker process ended"
            if code in (0, None) and self._stopped
            else f"the session's worker process died ({_describe_exit(code)})"
        )
        with self._wake:
            self._lost = reason
            waiting, self._calls = list(self._calls.values()), {}
            self._outgoing.clear()
            self._wake.notify_all()
        for future in waiting:
            future.set_exception(WorkerLost(reason))
        self._conn.close()
        on_lost = self.on_lost
        # The listeners hold the session, which holds this worker: let go, so that a closed
        # session is freed at once rather than at Python's next cyclic collection.
        self.on_update = self.on_lost = _ignore
        if not self._stopped:
            on_lost(reason)

    # ------------------------------------------------------------------ the end
    def stop(self, save: bool, timeout_s: float = 120.0) -> dict:
        """Stop the session (final snapshot when ``save``) and let the process end. Raises
        SnapshotError when the save failed: the worker then stays, to be stopped again."""
        self._stopped = True
        try:
            meta = self.call("stop", save, timeout_s=timeout_s)
        except Exception:
            if self.process.is_alive():
                self._stopped = False
            raise
        self.process.join(timeout=10)
        self._end_helpers()
        return meta

    def kill(self) -> None:
        """End the process at once (a session deleted, or one whose worker stopped answering)."""
        self._stopped = True
        if self.process.is_alive():
            self.process.kill()
        self.process.join(timeout=10)
        self._end_helpers()

    def _end_helpers(self) -> None:
        """The helper processes (mapper, loops) end when their worker closes its pipes; make
        sure. A shared room's mapper serves the phones that joined it on (``room_shared``):
        whoever reaps it (``SharedRooms``) takes it."""
        for process in self.helpers():
            if process is self.mapper_process and self.room_shared:
                continue
            process.join(timeout=10)
            if process.is_alive():
                process.kill()
                process.join(timeout=10)

    def helpers(self) -> list:
        """The session's processes beside its worker: the mapper, and the loop process."""
        return [p for p in (self.mapper_process, self.loops_process) if p is not None]


def _ignore(*_) -> None:
    pass


def _describe_exit(code: int | None) -> str:
    if code is None:
        return "still running, not answering"
    if code < 0:
        try:
            return f"killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"killed by signal {-code}"
    return f"exit code {code}"


_CONTEXT = None
_CONTEXT_LOCK = threading.Lock()
_RUNNING: weakref.WeakSet[ProcessWorker] = weakref.WeakSet()


@atexit.register
def _kill_leftovers() -> None:
    """Workers ignore SIGTERM (see _worker_main), so multiprocessing's own exit handler, which
    terminates daemon children with it and then joins them, would wait forever for any still
    running: a server stops its sessions before it exits, so these are leftovers; kill them.
    (Registered after multiprocessing's handler, so it runs before it.)"""
    for worker in list(_RUNNING):
        for process in (worker.process, *worker.helpers()):
            if process.is_alive():
                process.kill()


def _context():
    """The forkserver context, its server preloaded with the session stack (once per process)."""
    global _CONTEXT
    with _CONTEXT_LOCK:
        if _CONTEXT is None:
            ctx = multiprocessing.get_context("forkserver")
            ctx.set_forkserver_preload(_PRELOAD)
            _CONTEXT = ctx
        return _CONTEXT


def process_context() -> multiprocessing.context.ForkServerContext:
    """The forkserver context the session workers come from (its server has the numerical
    stack imported): for other work kept out of the web process, e.g. converting an upload."""
    return _context()


def _nothing() -> None:
    pass


def warm_up() -> None:
    """Start the forkserver and wait until it has imported the session stack (seconds), so
    that the first session does not wait for it."""
    process = _context().Process(target=_nothing, name="warm-up", daemon=True)
    process.start()
    process.join()
