"""All sessions of a server: creation with a capacity cap, token checks, closing, restoring, and
sessions whose worker died."""

from __future__ import annotations

import hmac
import logging
import os
import secrets
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

from server.sessions.config import SessionConfig, threads_per_session
from server.sessions.errors import SessionError, SnapshotError
from server.sessions.processes.session_process import ProcessWorker
from server.sessions.runtime.host import HostArgs
from server.sessions.runtime.session import ROOM_FOLDER
from server.sessions.store import SessionStore, StoreError, hash_token
from server.sessions.web.live import LiveSession, SessionWorker
from server.sessions.web.shared_rooms import SharedRooms

log = logging.getLogger(__name__)

JOINED_ROOM = "joined_room"  # in a joined session's folder: the room as it stood at the join

_NO_SESSION_HASH = hash_token(secrets.token_urlsafe(32))  # compared against for unknown ids


@dataclass
class FoundSession:
    """A live session found on a shared cluster (``workers.find``): who owns it, and how to
    attach this front-end to its worker."""

    token_hash: str
    created_at: float
    attach: Callable[[LiveSession], SessionWorker]  # -> the worker, delivering to this session


class WorkerBackend(Protocol):
    """Where sessions' workers run: ``ProcessWorkers`` or ``server.sessions.processes.ray_workers``'
    ``RayWorkers``."""

    kind: str

    def start(self, args: HostArgs, session: LiveSession) -> SessionWorker:
        """A new worker for ``session``, delivering its updates to it."""
        ...

    def find(self, session_id: str) -> FoundSession | None:
        """A live session this front-end did not start, or None."""
        ...

    def detach(self) -> None:
        """The front-end is going away: let go of the sessions that outlive it."""
        ...

    def close(self) -> None: ...


class ProcessWorkers:
    """Runs each session in a local worker process (the default;
    ``server.sessions.processes.ray_workers`` runs them as Ray actors instead). Its workers are
    ``server.sessions.processes.session_process.ProcessWorker``s (a ``SessionWorker``)."""

    kind = "process"

    def start(self, args: HostArgs, session: LiveSession) -> ProcessWorker:
        return ProcessWorker(args, session.deliver, session.lost)

    def find(self, session_id: str) -> FoundSession | None:
        """A live session this front-end did not start: another front-end's, or its own
        before a restart. Local processes die with their front-end: never any."""
        return None

    def detach(self) -> None:
        """Local processes end with their front-end: no session outlives it."""

    def close(self) -> None:
        pass


class SessionManager:
    """Live sessions in memory; closed ones on disk under the store, loaded back on start.

    ``threads``: native threads per session's libraries; 0 shares the cores among the live
    sessions (rebalanced as sessions come and go)."""

    def __init__(
        self,
        store: SessionStore,
        config: SessionConfig | None = None,
        max_sessions: int = 16,
        workers: WorkerBackend | None = None,
        threads: int = 0,
        max_room_phones: int = 3,
    ) -> None:
        self.store = store
        self.config = config or SessionConfig.from_config()
        self.max_sessions = max_sessions
        self.workers: WorkerBackend = workers or ProcessWorkers()
        self.threads = threads
        self.faults: dict[str, list[int]] | None = None  # tests: HostArgs.faults of new sessions
        self._live: dict[str, LiveSession] = {}
        self._saved: dict[str, dict] = {}  # id -> meta of closed sessions
        self._closing: set[str] = set()  # live sessions being stopped and saved
        self._lock = threading.Lock()
        self.rooms = SharedRooms(max_room_phones, self.live_session, self.store.folder)

    # ------------------------------------------------------------------ lifecycle
    def load_saved(self, writers_timeout_s: float = 60.0) -> int:
        """Index the sessions a previous run left on disk (closed, downloadable), and remove
        the partial files of writes it cut short, once its session processes have ended (a
        killed server's mapper finishes the snapshot it was writing first); after
        ``writers_timeout_s`` without that, the partial files are left where they are."""
        t0 = time.monotonic()
        clean = self.store.wait_for_writers(writers_timeout_s)
        if clean and time.monotonic() - t0 > 0.1:
            log.warning(
                "waited %.1f s for the session processes of an earlier run to end",
                time.monotonic() - t0,
            )
        if not clean:
            log.error(
                "processes of an earlier run still write under %s after %.0f s: partial files "
                "of interrupted writes are left in place",
                self.store.root,
                writers_timeout_s,
            )
        for sid in self.store.saved_ids():
            try:
                self._saved[sid] = self.store.read_meta(sid)
            except StoreError as exc:
                log.warning("skipping saved session: %s", exc)
                continue
            removed = self.store.remove_partial_files(sid) if clean else []
            if removed:
                log.warning(
                    "session %s: removed %d partial files of an interrupted write: %s",
                    sid,
                    len(removed),
                    ", ".join(removed),
                )
        return len(self._saved)

    def _threads_each(self, sessions: int) -> int:
        return self.threads or threads_per_session(os.cpu_count() or 1, sessions)

    def room_of(self, room_id: str, token: str | None) -> Path:
        """The room folder a closed session ``room_id`` left, if ``token`` is that session's.
        SessionError not_found (as ``authorize``) for a wrong id or token, room_unavailable when
        the session is live or saved no room (no keyframe, or no map)."""
        entry = self.authorize(room_id, token)
        folder = self.store.folder(room_id) / ROOM_FOLDER
        # A live session has no room yet; one whose final save is done has (its status says
        # closed before this manager has moved it to the saved ones).
        live = isinstance(entry, LiveSession) and entry.final_meta is None
        if live or not (folder / "room.json").is_file():
            raise SessionError(
                "room_unavailable",
                "that session has saved no room: a room is saved when a session that mapped "
                "something closes",
            )
        return folder

    def create(
        self,
        room: Path | None = None,
        loop_closure: bool | None = None,
        joining: LiveSession | None = None,
    ) -> tuple[LiveSession, str]:
        """A new live session, its worker started, and its secret token (shown once; only its
        hash is kept). room: a room folder (``room_of``) for the session to continue in.
        loop_closure: online loop closure on or off in this session (None: the server's
        ``registration.loops.live``); ``closes_loops`` says whether it runs. joining: a live
        session (``SharedRooms.room_to_join``) whose room, as it stands, the new session
        continues in (SessionError room_unavailable while that room has mapped nothing)."""
        with self._lock:
            if len(self._live) + len(self._closing) >= self.max_sessions:
                raise SessionError(
                    "server_full",
                    f"the server holds its maximum of "
                    f"{self.max_sessions} live sessions; try again later",
                )
            sid = secrets.token_hex(8)
            while sid in self._live or sid in self._saved:
                sid = secrets.token_hex(8)
            self._closing.add(sid)  # holds its place while the worker starts
            threads = self._threads_each(len(self._live) + 1)
        if joining is not None:
            try:
                room = self.rooms.share(joining, self.store.folder(sid) / JOINED_ROOM)
            except BaseException:
                with self._lock:
                    self._closing.discard(sid)
                raise
        token = secrets.token_urlsafe(32)
        args = HostArgs(
            sid,
            hash_token(token),
            str(Path(self.store.root).parent),
            self.config.with_loop_closure(loop_closure),
            time.time(),
            threads,
            self.faults,
            None if room is None else str(room),
            # The room's one map, where the room's worker offers one (process workers do).
            room_map=None if joining is None else getattr(joining.worker, "room_map", None),
        )
        try:
            session = LiveSession(
                sid,
                args.token_hash,
                args.created_at,
                lambda s: self.workers.start(args, s),
                self.session_lost,
                self.session_failed,
            )
            session.worker.call("save_meta")
        except BaseException:
            with self._lock:
                self._closing.discard(sid)
            raise
        with self._lock:
            self._closing.discard(sid)
            self._live[sid] = session
        if joining is not None:
            self.rooms.joined(joining.id, sid)
        self._rebalance()
        return session, token

    def closes_loops(self, room: Path | None = None, loop_closure: bool | None = None) -> bool:
        """Whether a session created with these arguments runs online loop closure."""
        return self.config.with_loop_closure(loop_closure).closes_loops(in_room=room is not None)

    def _rebalance(self) -> None:
        """Share the cores among the live sessions' thread pools (when ``threads`` is auto)."""
        if self.threads:
            return
        with self._lock:
            sessions = list(self._live.values())
        each = self._threads_each(len(sessions))
        for session in sessions:
            try:
                session.worker.call("set_threads", each, timeout_s=10)
            except SessionError:
                pass  # a worker that died is reported by its own path

    def session_lost(self, session: LiveSession, reason: str) -> None:
        """A worker died on its own: the session is closed and kept as its last snapshot left
        it (the meta on disk, marked failed), downloadable as before."""
        log.error("session %s: %s; closed, kept as of its last snapshot", session.id, reason)
        with self._lock:
            if self._live.get(session.id) is not session:
                return
            del self._live[session.id]
        try:
            meta = self.store.read_meta(session.id)
        except StoreError:
            meta = {
                "id": session.id,
                "token_sha256": session.token_hash,
                "created_at": session.created_at,
                "status": {},
            }
        # A worker killed mid-snapshot leaves its staging folder and temp files behind, as a
        # killed server does; the committed snapshot beside them is whole.
        try:
            removed = self.store.remove_partial_files(session.id)
        except OSError:
            removed = []
        if removed:
            log.warning("session %s: removed partial files %s", session.id, ", ".join(removed))
        meta["closed"] = True
        meta["failure"] = reason
        meta["status"] = dict(meta.get("status") or {}, closed=True, failure=reason)
        try:
            self.store.write_meta(session.id, meta)
        except OSError as exc:
            log.error("session %s: could not mark it failed on disk (%s)", session.id, exc)
        with self._lock:
            self._saved[session.id] = meta
        self._rebalance()

    def session_failed(self, session: LiveSession, reason: str) -> None:
        """A session failed in its live worker (its map is gone): stop and save it now, off the
        caller's thread (the worker's reader). A save that fails is retried by the reaper, as
        for any closed session."""
        log.error("session %s: %s; stopping and saving it", session.id, reason)
        threading.Thread(
            target=self.close, args=(session.id,), name=f"close-{session.id}", daemon=True
        ).start()

    def authorize(self, session_id: str, token: str | None) -> LiveSession | dict:
        """The live session, or the saved meta of a closed one, that ``token`` opens.

        Unknown ids and wrong tokens raise the same error after the same work (one hash, one
        constant-time comparison of hashes), so a stranger learns nothing about which sessions
        exist."""
        if token is None:
            raise SessionError("unauthorized", "this request needs the session's token")
        with self._lock:
            found = self._live.get(session_id)
            saved = self._saved.get(session_id)
        if found is None and not (saved or {}).get("closed"):
            # Unknown here, or on disk but never closed: maybe live on the cluster.
            found = self._adopt(session_id)
        entry: LiveSession | dict | None = found or saved
        if isinstance(entry, LiveSession):
            expected = entry.token_hash
        else:
            expected = (entry or {}).get("token_sha256", _NO_SESSION_HASH)
        if hmac.compare_digest(hash_token(token), expected) and entry is not None:
            return entry
        raise SessionError("not_found", "no session with this id for this token")

    def live_session(self, session_id: str) -> LiveSession | None:
        """The live session with this id held here, or None (viewer links check their own
        token against it: ``LiveSession.viewers``)."""
        with self._lock:
            return self._live.get(session_id)

    def _adopt(self, session_id: str) -> LiveSession | None:
        """A live session this front-end did not start (another front-end of the same cluster,
        or this one before a restart), found by its id."""
        try:
            found = self.workers.find(session_id)
        except Exception:  # a cluster that does not answer: as if the session were unknown
            log.exception("looking up session %s on the cluster failed", session_id)
            return None
        if found is None:
            return None
        session = LiveSession(
            session_id,
            found.token_hash,
            found.created_at,
            found.attach,
            self.session_lost,
            self.session_failed,
        )
        with self._lock:
            return self._live.setdefault(session_id, session)

    def close(self, session_id: str) -> bool:
        """Stop a live session and keep its map and trajectory on disk; False when it could not
        be saved (it then stays in memory, closed to frames, and a later close tries again).

        While it stops and saves (seconds for a large map) it stays reachable with its token,
        marked closed, so that its owner never sees it vanish; a session deleted meanwhile
        stays deleted."""
        with self._lock:
            session = self._live.get(session_id)
            if session is None or session_id in self._closing:
                return False
            self._closing.add(session_id)
            session.closed = True  # a hello now gets "closed"; frames no longer arrive
        meta: dict | None = None  # the saved meta, once saved
        try:
            meta = session.stop(save=True)
        except SnapshotError as exc:
            log.error("%s: the session stays in memory, closed to frames; retrying later", exc)
        except SessionError as exc:  # the worker died while stopping: keep its last snapshot
            self.session_lost(session, str(exc))
            return False
        finally:
            with self._lock:
                self._closing.discard(session_id)
                deleted = session_id not in self._live
                if meta is not None and not deleted:
                    del self._live[session_id]
                    self._saved[session_id] = meta
        saved = meta is not None
        if deleted:
            self.store.delete(session_id)  # the final snapshot wrote after the delete
        if saved:
            self._rebalance()
        return saved

    def delete(self, session_id: str) -> None:
        """Stop a session if live and remove all its data."""
        with self._lock:
            session = self._live.pop(session_id, None)
            self._saved.pop(session_id, None)
        if session is not None:
            session.stop(save=False)
            self._rebalance()
        self.store.delete(session_id)

    def reap(self, ttl_s: float, connected: set[str]) -> list[str]:
        """Close live sessions with no connection and no frame for ``ttl_s`` seconds (and retry
        those whose save failed). Returns the ids closed and saved."""
        now = time.monotonic()
        with self._lock:
            idle = [
                (sid, s.closed)
                for sid, s in self._live.items()
                if sid not in connected and (s.closed or now - s.last_seen > ttl_s)
            ]
        closed = []
        for sid, unsaved in idle:
            log.info(
                "session %s %s",
                sid,
                "retrying its save" if unsaved else f"idle for {ttl_s:.0f} s: closing",
            )
            if self.close(sid):
                closed.append(sid)
        return closed

    def shutdown(self) -> list[str]:
        """Close every live session, saving each; returns the ids that could not be saved (not
        those another thread, the reaper, is still closing)."""
        self.rooms.close()
        with self._lock:
            live = list(self._live)
        if live:
            # Each worker saves in its own process: in parallel, a stop takes the slowest save.
            with ThreadPoolExecutor(max_workers=len(live)) as pool:
                list(pool.map(self.close, live))
        with self._lock:
            return [sid for sid in self._live if sid not in self._closing]

    # ------------------------------------------------------------------ queries
    @property
    def live_count(self) -> int:
        return len(self._live)

    @property
    def saved_count(self) -> int:
        return len(self._saved)
