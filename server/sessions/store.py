"""Session files under the data directory, every write atomic (temp file + rename).

Layout: ``<data_dir>/sessions/<id>/`` with ``meta.json``, ``trajectory.tum``, ``map.npz`` (the
TSDF), ``map.ply`` (its surface points, ready to download), ``course_best.json`` (the drone's best
course runs, written by the session as runs finish: ``server/sessions/runtime/course_control.py``)
and ``flights/`` (the drone's flight recordings, written by ``server/sessions/flight_store.py``).
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
import re
import shutil
import time
from pathlib import Path

from server.atomic import atomic_write_bytes
from server.errors import DroneSimError

SESSION_ID = re.compile(r"[0-9a-f]{16}")  # used with fullmatch: "$" would let a "\n" through
FILES = (
    "trajectory.tum",
    "map.npz",
    "map.ply",
    "meta.json",
    "course_best.json",
    "race_best.json",  # a shared room's races (server/sessions/race_results.py)
    "races.json",
)
STAGING = ".snapshot"  # inside a session's folder: the snapshot being written
# In the sessions folder: held shared by every process that writes sessions' files (the workers,
# the mappers) for as long as it lives; a starting server takes it exclusively before it cleans.
WRITERS_LOCK = ".writers.lock"


def hold_writers_lock(data_dir: str | Path) -> int:
    """This process writes sessions' files under ``data_dir``: hold the writers lock (shared)
    until it ends, whichever way (the kernel lets go of it with the process, killed or not).
    Returns the lock's file descriptor, to keep open."""
    root = Path(data_dir) / "sessions"
    root.mkdir(parents=True, exist_ok=True)
    fd = os.open(root / WRITERS_LOCK, os.O_RDWR | os.O_CREAT, 0o600)
    fcntl.flock(fd, fcntl.LOCK_SH)
    return fd


def hash_token(token: str) -> str:
    """What a session keeps of its token (sha256, hex): the token itself is never stored."""
    return hashlib.sha256(token.encode()).hexdigest()


class StoreError(DroneSimError):
    """A session's files are missing or unreadable."""


class SessionStore:
    """Where sessions' files live. Ids are checked against a strict pattern before any path is
    built, so no id can reach outside the data directory."""

    def __init__(self, data_dir: Path) -> None:
        self.root = Path(data_dir) / "sessions"
        self.root.mkdir(parents=True, exist_ok=True)

    def folder(self, session_id: str) -> Path:
        if not isinstance(session_id, str) or not SESSION_ID.fullmatch(session_id):
            raise StoreError("malformed session id")
        return self.root / session_id

    def write_meta(self, session_id: str, meta: dict) -> None:
        atomic_write_bytes(
            self.folder(session_id) / "meta.json", json.dumps(meta, indent=2).encode()
        )

    def staging(self, session_id: str, create: bool = True) -> Path:
        """A folder to write a whole snapshot into; :meth:`commit` moves it into place."""
        path = self.folder(session_id) / STAGING
        if create:
            path.mkdir(parents=True, exist_ok=True)
        return path

    def commit(self, session_id: str, names: list[str], meta: dict) -> None:
        """Move the staged files ``names`` into place, then write ``meta``. Writing a large map
        takes a second; the renames take microseconds, so a crash leaves the previous snapshot or
        the new one (at worst a mix of whole files), and the meta, written last, never counts
        fewer frames than the trajectory beside it holds."""
        staging = self.staging(session_id, create=False)
        for name in names:
            os.replace(staging / name, self.file(session_id, name))
        self.write_meta(session_id, meta)
        shutil.rmtree(staging, ignore_errors=True)  # leaves the folder as a reader expects it

    def wait_for_writers(self, timeout_s: float) -> bool:
        """Wait until no process holds the writers lock (``hold_writers_lock``): a killed
        server's session processes outlive it, a mapper finishing the snapshot it was writing
        (seconds on a busy machine) before it ends, and their files must not be cleaned away
        from under them. True once none is left; False after ``timeout_s``."""
        fd = os.open(self.root / WRITERS_LOCK, os.O_RDWR | os.O_CREAT, 0o600)
        deadline = time.monotonic() + timeout_s
        try:
            while True:
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                    return True  # let go with the close: this run's processes take it shared
                except BlockingIOError:
                    if time.monotonic() >= deadline:
                        return False
                    time.sleep(0.05)
        finally:
            os.close(fd)

    def read_meta(self, session_id: str) -> dict:
        path = self.folder(session_id) / "meta.json"
        try:
            return json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            raise StoreError(f"session {session_id}: unreadable meta.json ({exc})") from exc

    def file(self, session_id: str, name: str) -> Path:
        """Path of one of the session's files (``FILES``)."""
        if name not in FILES:
            raise StoreError(f"unknown session file {name!r}")
        return self.folder(session_id) / name

    def saved_ids(self) -> list[str]:
        return sorted(
            p.name
            for p in self.root.iterdir()
            if SESSION_ID.fullmatch(p.name) and (p / "meta.json").is_file()
        )

    def remove_partial_files(self, session_id: str) -> list[str]:
        """Delete temp files that a write cut short by a crash left beside the session's files,
        and a snapshot staged but not committed (the files themselves are whole: each was
        renamed into place). Call only while the session is not live, and no process of an
        earlier run writes any more (``wait_for_writers``). Returns the names removed."""
        prefixes = tuple(f".{name}." for name in FILES)  # as the atomic writers name them
        partial = [
            p
            for p in self.folder(session_id).iterdir()
            if p.is_file() and p.name.startswith(prefixes)
        ]
        flights = self.folder(session_id) / "flights"  # server/sessions/flight_store.py
        if flights.is_dir():  # its writes' temporary files start with a dot too
            partial += [p for p in flights.iterdir() if p.is_file() and p.name.startswith(".")]
        for path in partial:
            path.unlink(missing_ok=True)
        staged = self.staging(session_id, create=False)  # a snapshot never committed
        if staged.is_dir():
            shutil.rmtree(staged, ignore_errors=True)
            partial.append(staged)
        return [p.name for p in partial]

    def delete(self, session_id: str) -> None:
        shutil.rmtree(self.folder(session_id), ignore_errors=True)
