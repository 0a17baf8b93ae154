"""How a session's processes talk: one request and reply shape, one error convention, one serve
loop and one calling helper, shared by the worker, the mapper and the loop process (and the
reply shape by the Ray actors).

- A request is ``(call_id, method, args)``; call_id None for one that wants no answer.
- A reply is ``("reply", call_id, ok, value)``: the method's value, or the exception it raised as
  a :class:`RemoteError`, plain values that pickle whatever the exception class looks like. The
  caller raises it again with :func:`raise_remote` as the class the web side answers for
  (SessionError, CommandRefused, ProtocolError, SnapshotError, MapError, OSError; anything else,
  a bug, as the process's internal failure, its traceback logged where it was raised).
- A process that is gone is the caller's own "lost" error (WorkerLost, MapperLost,
  LoopProcessError), which is what the session's code catches.

``serve`` runs in the process that owns the object called (its *target*); a ``Proxy`` is the
caller's handle on it, one call at a time.
"""

from __future__ import annotations

import itertools
import logging
import queue
import signal
import threading
from collections import deque
from collections.abc import Callable, Collection
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from server import protocol as proto
from server.mapping.tsdf import MapError
from server.sessions.errors import CommandRefused, SessionError, SnapshotError
from server.sessions.processes.priority import lower_this_threads_priority

REPLY = "reply"  # the tag of a reply (a worker's pipe also carries ("update", item))


# ---- errors as values -------------------------------------------------------------------------


@dataclass
class RemoteError:
    """An exception raised in another process, as plain values (``kind`` names its class)."""

    kind: str
    code: str
    message: str
    nearest: list[float] | None = None


def as_remote(exc: BaseException) -> RemoteError:
    if isinstance(exc, CommandRefused):
        nearest = None if exc.nearest is None else [float(v) for v in exc.nearest]
        return RemoteError("command", exc.code, str(exc), nearest)
    if isinstance(exc, SessionError):
        return RemoteError("session", exc.code, str(exc))
    if isinstance(exc, proto.ProtocolError):
        return RemoteError("protocol", exc.code, str(exc))
    if isinstance(exc, SnapshotError):
        return RemoteError("snapshot", "snapshot_failed", str(exc))
    if isinstance(exc, MapError):
        return RemoteError("map", "map_unavailable", str(exc))
    if isinstance(exc, OSError):  # a disk that refuses a snapshot: the caller keeps its data
        return RemoteError("os", type(exc).__name__, str(exc))
    return RemoteError("internal", "internal_error", f"{type(exc).__name__}: {exc}")


def raise_remote(error: RemoteError, where: str = "the session's worker") -> None:
    """Raise, on the caller's side, the exception a call raised in the process ``where``."""
    if error.kind == "command":
        nearest = None if error.nearest is None else np.asarray(error.nearest)
        raise CommandRefused(error.code, error.message, nearest)
    if error.kind == "session":
        raise SessionError(error.code, error.message)
    if error.kind == "protocol":
        raise proto.ProtocolError(error.code, error.message)
    if error.kind == "snapshot":
        raise SnapshotError(error.message)
    if error.kind == "map":
        raise MapError(error.message)
    if error.kind == "os":
        raise OSError(f"{error.code}: {error.message}")
    raise RuntimeError(f"{where} failed: {error.message}")


def attempt(target: object, method: str, args: tuple, log: logging.LoggerAdapter | logging.Logger):
    """Call ``target.method(*args)``: ``(True, its value)`` or ``(False, its RemoteError)``. A bug
    (an internal error, not an answer such as a refused command) is logged with its traceback."""
    try:
        return True, getattr(target, method)(*args)
    except Exception as exc:
        error = as_remote(exc)
        if error.kind == "internal":
            log.exception("%s failed", method)
        return False, error


def result(ok: bool, value, where: str = "the session's worker"):
    """A reply's value, or its error raised (``raise_remote``)."""
    if not ok:
        raise_remote(value, where)
    return value


def reply(call_id: int, ok: bool, value) -> tuple:
    return (REPLY, call_id, ok, value)


# ---- the process that serves --------------------------------------------------------------------


def prepare_child(nice: int = 0) -> None:
    """The start of a session's process: a Ctrl-C or SIGTERM meant for the server reaches the
    whole process group, but this process's owner decides when it ends (after a final save);
    and its priority lowered by ``nice`` (tracking first, then the map, then loop closing)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    if nice:
        lower_this_threads_priority(nice)


def serve(
    target: object,
    conn,
    log: logging.LoggerAdapter | logging.Logger,
    *,
    send: Callable[[tuple], None] | None = None,
    ordered: Collection[str] | None = None,
    beside: int = 0,
    last: str | None = None,
) -> bool:
    """Answer the requests arriving on ``conn`` with ``target``'s methods until the pipe closes
    (returns False at once: the caller is gone) or a call to ``last`` succeeds (returns True,
    once the calls beside have answered). Replies go through ``send`` (default ``conn.send``;
    a send that fails ends the loop as a closed pipe does).

    Calls run in arrival order on this thread, except, when ``ordered`` is given, the methods
    not in it, which run on ``beside`` threads of their own so that they never hold up the
    ordered ones (a worker's status query beside its frames), nor wait for them: a reader
    thread takes every request off the pipe as it comes, so a query is answered while an
    ordered call runs (a status while the stop writes the final snapshot, seconds on a busy
    machine)."""
    send = conn.send if send is None else send

    def answer(call_id: int | None, method: str, args: tuple) -> bool:
        ok, value = attempt(target, method, args, log)
        if call_id is not None:
            send(reply(call_id, ok, value))
        return ok

    if ordered is None or beside <= 0:
        try:
            while True:
                try:
                    call_id, method, args = conn.recv()
                except (EOFError, OSError):
                    return False
                if answer(call_id, method, args) and method == last:
                    return True
        except (OSError, ValueError):  # the reply could not go: the caller is gone
            return False

    side = ThreadPoolExecutor(max_workers=beside, thread_name_prefix="query")
    calls: queue.SimpleQueue[tuple | None] = queue.SimpleQueue()  # the ordered ones; None: EOF

    def read() -> None:
        while True:
            try:
                call = conn.recv()
            except (EOFError, OSError):
                calls.put(None)
                return
            if call[1] in ordered:
                calls.put(call)
            else:
                try:
                    side.submit(answer, *call)
                except RuntimeError:  # shut down: the loop below has ended
                    return

    threading.Thread(target=read, name="requests", daemon=True).start()
    ended = False
    try:
        while (call := calls.get()) is not None:
            if answer(*call) and call[1] == last:
                ended = True
                return True
        return False
    except (OSError, ValueError):  # the reply could not go: the caller is gone
        return False
    finally:
        side.shutdown(wait=ended)


# ---- the caller ---------------------------------------------------------------------------------


class TurnLock:
    """A lock taken in the order it was asked for. A plain ``threading.Lock`` is not: a thread
    that releases it and asks again at once (the mapping thread, fusing frame after frame)
    mostly wins over one that waits, and on a busy machine a download or a status query waited
    behind dozens of fusions (seconds; tests/unit/sessions/test_ipc.py measures it). Here the
    holder hands the lock to the longest waiter."""

    def __init__(self) -> None:
        self._guard = threading.Lock()
        self._held = False
        self._waiting: deque[threading.Lock] = deque()

    def acquire(self, blocking: bool = True) -> bool:
        with self._guard:
            if not self._held:
                self._held = True
                return True
            if not blocking:
                return False
            turn = threading.Lock()
            turn.acquire()
            self._waiting.append(turn)
        try:
            turn.acquire()  # released by the holder that hands over: the lock is ours, still held
        except BaseException:  # a signal's handler raised in the wait (the main thread's)
            with self._guard:
                if turn in self._waiting:  # not our turn yet: leave the queue
                    self._waiting.remove(turn)
                    raise
            self.release()  # handed over meanwhile: pass it on, never left held by no one
            raise
        return True

    def release(self) -> None:
        with self._guard:
            if self._waiting:
                self._waiting.popleft().release()
            else:
                self._held = False

    def __enter__(self) -> TurnLock:
        self.acquire()
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


class Proxy:
    """The caller's handle on a target served in another process at the other end of ``conn``,
    one call at a time, in the order the callers asked (``call_if_idle`` never waits for
    another). When that process is gone, each call raises ``lost(message)``, the caller's own
    error for it; ``where`` names the process."""

    def __init__(self, conn, lost: Callable[[str], Exception], where: str) -> None:
        self._conn = conn
        self._lost = lost
        self.where = where
        self._lock = TurnLock()
        self._ids = itertools.count(1)

    def call(self, method: str, *args):
        """Run ``method`` there and return its value (or raise its error)."""
        with self._lock:
            return self._call_holding_lock(method, args)

    def call_if_idle(self, method: str, *args) -> tuple[bool, object]:
        """As ``call`` when no other call is in progress: ``(True, its value)``; else
        ``(False, None)`` at once, never waiting for the call in progress."""
        if not self._lock.acquire(blocking=False):
            return False, None
        try:
            return True, self._call_holding_lock(method, args)
        finally:
            self._lock.release()

    def _call_holding_lock(self, method: str, args: tuple):
        call_id = next(self._ids)
        try:
            self._conn.send((call_id, method, args))
            _, answered, ok, value = self._conn.recv()
        except (EOFError, OSError, ValueError) as exc:
            raise self._lost(f"{self.where} is gone ({exc})") from None
        if answered != call_id:  # one call at a time: a reply out of turn is a broken pipe
            raise self._lost(f"{self.where} answered call {answered} for call {call_id}")
        return result(ok, value, self.where)

    def close(self) -> None:
        """Let the process end (it ends when its pipe closes)."""
        with self._lock:
            self._conn.close()
