"""A session's flight recordings on disk: ``<data_dir>/sessions/<id>/flights/``.

Each flight is one JSON file, ``<flight id>.json`` (``FlightRecording.as_dict``, documented in
shared/PROTOCOL.md), and ``index.json`` lists their summaries, newest last. Every write is
atomic (a temporary file renamed into place), the flight before the index, so the index never
names a flight that is not whole on disk. The worker writes (a flight as it closes, the flight
in progress with every snapshot and at the end); the web process only reads.

Size: a flight is kept up to ``max_flight_s`` of states and a session keeps its newest
``flights_kept`` flights (older files are deleted as new ones are saved).
"""

from __future__ import annotations

import json
import re
import threading
from pathlib import Path

from server.atomic import atomic_write_bytes
from server.sessions.store import SessionStore, StoreError
from server.simulation.flight_recording import FlightRecorder, FlightRecording, summary

FLIGHT_ID = re.compile(r"[1-9][0-9]{0,8}")  # fullmatch: flight numbers 1, 2, ... per session
FOLDER = "flights"
INDEX = "index.json"


class FlightNotFound(StoreError):
    """No flight with this id in this session (or a malformed id)."""


def flights_folder(store: SessionStore, session_id: str) -> Path:
    return store.folder(session_id) / FOLDER


def read_index(store: SessionStore, session_id: str) -> list[dict]:
    """The summaries of the session's saved flights, oldest first ([] before the first)."""
    path = flights_folder(store, session_id) / INDEX
    try:
        return json.loads(path.read_bytes())["flights"]
    except FileNotFoundError:
        return []
    except (OSError, ValueError, KeyError) as exc:
        raise StoreError(f"session {session_id}: unreadable flight index ({exc})") from exc


def flight_path(store: SessionStore, session_id: str, flight_id: str) -> Path:
    """The JSON file of one saved flight; FlightNotFound when there is none."""
    if not isinstance(flight_id, str) or not FLIGHT_ID.fullmatch(flight_id):
        raise FlightNotFound(f"no flight {flight_id!r} in this session")
    path = flights_folder(store, session_id) / f"{flight_id}.json"
    if not path.is_file():
        raise FlightNotFound(f"no flight {flight_id!r} in this session")
    return path


def read_flight(store: SessionStore, session_id: str, flight_id: str) -> dict:
    path = flight_path(store, session_id, flight_id)
    try:
        return json.loads(path.read_bytes())
    except (OSError, ValueError) as exc:
        raise StoreError(f"session {session_id}: unreadable flight {flight_id} ({exc})") from exc


class FlightLog:
    """The worker's side: records the session's flights (``recorder``, fed by ``Flight``) and
    saves each to the store. Writes happen on the thread that closes a flight (the flight
    thread at a landing), on the mapping thread with each snapshot (``save_open``), and on the
    main thread at the end (``close``); ``_lock`` keeps the index consistent between them."""

    def __init__(
        self,
        store: SessionStore,
        session_id: str,
        state_hz: float,
        max_flight_s: float,
        flights_kept: int,
    ) -> None:
        self.store = store
        self.session_id = session_id
        self.flights_kept = flights_kept
        self.saves_failed = 0  # flights the disk refused (the in-memory flight goes on)
        self._lock = threading.Lock()
        # Flights saved as ended: a snapshot's copy of one still in progress, taken just before
        # it ended on another thread, must not overwrite it.
        self._ended: set[str] = set()
        try:
            saved = read_index(store, session_id)
        except StoreError:
            saved = []
        first = 1 + max((int(f["id"]) for f in saved), default=0)
        self.recorder = FlightRecorder(state_hz, max_flight_s, self._closed, first_id=first)

    def _closed(self, flight: FlightRecording) -> None:
        try:
            self.save(flight.as_dict())
        except OSError:
            self.saves_failed += 1  # counted in the session's snapshots_failed; retried never:
            # the next snapshot writes the open flight only

    def save_open(self) -> None:
        """Write the flight in progress, if any (with every snapshot). Raises OSError."""
        flight = self.recorder.open_flight()
        if flight is not None:
            self.save(flight)

    def close(self) -> None:
        """The session ends: the open flight closes (``session_end``) and is saved."""
        self.recorder.close("session_end")

    def save(self, flight: dict) -> None:
        """Write one flight and the index (atomically, flight first); drop the oldest flights
        beyond ``flights_kept``. Raises OSError when the disk refuses."""
        folder = flights_folder(self.store, self.session_id)
        data = json.dumps(flight, separators=(",", ":")).encode()
        with self._lock:
            if flight["id"] in self._ended:
                return
            atomic_write_bytes(folder / f"{flight['id']}.json", data)
            if flight["finished"]:
                self._ended.add(flight["id"])
            try:
                index = read_index(self.store, self.session_id)
            except StoreError:
                index = []
            index = [f for f in index if f["id"] != flight["id"]]
            index.append(summary(flight) | {"bytes": len(data)})
            index.sort(key=lambda f: int(f["id"]))
            dropped, index = index[: -self.flights_kept], index[-self.flights_kept :]
            atomic_write_bytes(
                folder / INDEX, json.dumps({"flights": index}, separators=(",", ":")).encode()
            )
            for old in dropped:
                (folder / f"{old['id']}.json").unlink(missing_ok=True)
