"""All sessions of a server: creation with a capacity cap, token checks, closing, restoring."""

from __future__ import annotations

import hmac
import logging
import secrets
import threading
import time

from server.memory import release_session_memory
from server.sessions.errors import SnapshotError
from server.sessions.session import Session, SessionConfig, SessionError, hash_token
from server.sessions.store import SessionStore, StoreError

log = logging.getLogger(__name__)

_NO_SESSION_HASH = hash_token(secrets.token_urlsafe(32))  # compared against for unknown ids


class SessionManager:
    """Live sessions in memory; closed ones on disk under the store, loaded back on start."""

    def __init__(self, store: SessionStore, config: SessionConfig | None = None,
                 max_sessions: int = 16) -> None:
        self.store = store
        self.config = config or SessionConfig()
        self.max_sessions = max_sessions
        self._live: dict[str, Session] = {}
        self._saved: dict[str, dict] = {}  # id -> meta of closed sessions
        self._closing: set[str] = set()  # live sessions being stopped and saved
        self._lock = threading.Lock()

    # ------------------------------------------------------------------ lifecycle
    def load_saved(self) -> int:
        """Index the sessions a previous run left on disk (closed, downloadable)."""
        for sid in self.store.saved_ids():
            try:
                self._saved[sid] = self.store.read_meta(sid)
            except StoreError as exc:
                log.warning("skipping saved session: %s", exc)
                continue
            removed = self.store.remove_partial_files(sid)
            if removed:
                log.warning("session %s: removed %d partial files of an interrupted write: %s",
                            sid, len(removed), ", ".join(removed))
        return len(self._saved)

    def create(self) -> tuple[Session, str]:
        """A new live session and its secret token (shown once; only its hash is kept)."""
        with self._lock:
            if len(self._live) >= self.max_sessions:
                raise SessionError("server_full", f"the server holds its maximum of "
                                   f"{self.max_sessions} live sessions; try again later")
            sid = secrets.token_hex(8)
            while sid in self._live or sid in self._saved:
                sid = secrets.token_hex(8)
            token = secrets.token_urlsafe(32)
            session = Session(sid, hash_token(token), self.store, self.config)
            self._live[sid] = session
        session.store.write_meta(sid, session.meta())
        return session, token

    def authorize(self, session_id: str, token: str | None) -> Session | dict:
        """The live session, or the saved meta of a closed one, that ``token`` opens.

        Unknown ids and wrong tokens raise the same error after the same work (one hash, one
        constant-time comparison of hashes), so a stranger learns nothing about which sessions
        exist."""
        if token is None:
            raise SessionError("unauthorized", "this request needs the session's token")
        with self._lock:
            found = self._live.get(session_id) or self._saved.get(session_id)
        if isinstance(found, Session):
            expected = found.token_hash
        else:
            expected = (found or {}).get("token_sha256", _NO_SESSION_HASH)
        if hmac.compare_digest(hash_token(token), expected) and found is not None:
            return found
        raise SessionError("not_found", "no session with this id for this token")

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
        saved = False
        try:
            session.stop(save=True)
            saved = True
        except SnapshotError as exc:
            log.error("%s: the session stays in memory, closed to frames; retrying later", exc)
        finally:
            with self._lock:
                self._closing.discard(session_id)
                deleted = session_id not in self._live
                if saved and not deleted:
                    del self._live[session_id]
                    self._saved[session_id] = session.meta()
        if deleted:
            self.store.delete(session_id)  # the final snapshot wrote after the delete
        if saved or deleted:
            del session
            release_session_memory()
        return saved

    def delete(self, session_id: str) -> None:
        """Stop a session if live and remove all its data."""
        with self._lock:
            session = self._live.pop(session_id, None)
            self._saved.pop(session_id, None)
        if session is not None:
            session.stop(save=False)
            del session
            release_session_memory()
        self.store.delete(session_id)

    def reap(self, ttl_s: float, connected: set[str]) -> list[str]:
        """Close live sessions with no connection and no frame for ``ttl_s`` seconds (and retry
        those whose save failed). Returns the ids closed and saved."""
        now = time.monotonic()
        with self._lock:
            idle = [(sid, s.closed) for sid, s in self._live.items()
                    if sid not in connected and (s.closed or now - s.last_seen > ttl_s)]
        closed = []
        for sid, unsaved in idle:
            log.info("session %s %s", sid, "retrying its save" if unsaved
                     else f"idle for {ttl_s:.0f} s: closing")
            if self.close(sid):
                closed.append(sid)
        return closed

    def shutdown(self) -> list[str]:
        """Close every live session, saving each; returns the ids that could not be saved (not
        those another thread, the reaper, is still closing)."""
        for sid in list(self._live):
            self.close(sid)
        with self._lock:
            return [sid for sid in self._live if sid not in self._closing]

    # ------------------------------------------------------------------ queries
    @property
    def live_count(self) -> int:
        return len(self._live)

    @property
    def saved_count(self) -> int:
        return len(self._saved)
