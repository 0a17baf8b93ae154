"""The drone's side of a session's set-up: its flight (server/sessions/runtime/flight.py) and flight
log, made with the first hello, and the course's best list, carried over from a room."""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path

import numpy as np

from server.atomic import atomic_write_bytes
from server.geometry import Intrinsics
from server.sessions.config import SessionConfig
from server.sessions.failures import SessionLog
from server.sessions.flight_store import FlightLog
from server.sessions.race_results import RACE_BEST_FILE
from server.sessions.runtime.course_control import BEST_FILE as COURSE_BEST_FILE
from server.sessions.runtime.flight import Flight
from server.sessions.store import SessionStore, StoreError
from server.sessions.updates import Update


def course_best_path(store: SessionStore, session_id: str) -> Path | None:
    """Where the drone's course results are kept (None: an id the store cannot hold)."""
    try:
        return store.file(session_id, COURSE_BEST_FILE)
    except StoreError:
        return None


def best_list_paths(store: SessionStore, session_id: str) -> list[Path]:
    """The session's best lists that its room carries to later sessions: the course's and the
    room's races' (server/sessions/race_results.py); [] for an id the store cannot hold."""
    try:
        return [store.file(session_id, name) for name in (COURSE_BEST_FILE, RACE_BEST_FILE)]
    except StoreError:
        return []


def inherit_best(room_dir: Path, targets: list[Path], log: logging.LoggerAdapter) -> bool:
    """The best runs and races flown in the room so far become the session's best lists to
    beat (``targets``, ``best_list_paths``: pilots compete per room, not per visit); a room
    without any starts empty. False when the disk refused (logged)."""
    for target in targets:
        source = room_dir / target.name
        if not source.is_file() or target.exists():
            continue
        try:
            target.parent.mkdir(parents=True, exist_ok=True)
            atomic_write_bytes(target, source.read_bytes())
        except OSError:
            log.exception("the room's %s could not be carried over", target.name)
            return False
    return True


def make_flight(
    config: SessionConfig,
    store: SessionStore,
    session_id: str,
    intrinsics: Intrinsics,
    gravity: np.ndarray | None,
    publish: Callable[[Update], None],
) -> tuple[Flight, FlightLog]:
    """The drone of a session (``config.simulation`` set), and the log its flights are
    recorded into and saved from."""
    assert config.simulation is not None
    flight = Flight(
        config.simulation,
        intrinsics,
        gravity,
        publish,
        config.drone_state_hz,
        log=SessionLog(logging.getLogger("server.sessions.runtime.flight"), session_id),
    )
    flight_log = FlightLog(
        store, session_id, config.drone_state_hz, config.flight_max_s, config.flights_kept
    )
    flight.recorder = flight_log.recorder
    flight.course.best_path = course_best_path(store, session_id)
    return flight, flight_log
