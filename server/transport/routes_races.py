"""REST API for a shared room's finished races: the races a session flew in with its room's best
list, and every pilot's flights of one race, to replay them together.

A race's record is written into each of its pilots' session folders when it finishes
(server/sessions/race_results.py), so each pilot's own token opens it, live or saved; the
pilots' flights are read from their own folders (server/sessions/flight_store.py).
"""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter
from fastapi.responses import JSONResponse

from server.sessions import SessionError
from server.sessions.flight_store import FlightNotFound, read_flight, read_index
from server.sessions.race_results import (
    RACE_BEST_FILE,
    RACES_FILE,
    flights_in,
    race_record_named,
    read_races,
)
from server.sessions.runtime.course_control import read_best
from server.sessions.store import StoreError
from server.transport.deps import ManagerDep, SessionDep
from server.transport.schemas import RaceFlights, RaceList, error_response

router = APIRouter(prefix="/api/sessions", tags=["races"])

_ERRORS: dict[int | str, dict[str, Any]] = {
    401: error_response("no `Authorization: Bearer <token>` header"),
    404: error_response(
        "unknown session id, a token that does not open it, or no finished race with this "
        "number in this session"
    ),
}


@router.get("/{session_id}/races", response_model=RaceList, responses=_ERRORS)
def list_races(session_id: str, session: SessionDep, manager: ManagerDep) -> JSONResponse:
    """The shared-room races this session flew in (finished ones, oldest first), and its
    room's best list, carried over from earlier days with the room (PROTOCOL.md, "A shared
    room"). Empty before the first finished race."""
    del session  # the dependency checked the token
    folder = manager.store.folder(session_id)
    return JSONResponse(
        {"races": read_races(folder / RACES_FILE), "best": read_best(folder / RACE_BEST_FILE)}
    )


@router.get("/{session_id}/races/{number}/flights", response_model=RaceFlights, responses=_ERRORS)
def race_flights(
    session_id: str, number: int, session: SessionDep, manager: ManagerDep
) -> JSONResponse:
    """Every pilot's recorded flights of one race this session flew in, whole, to replay
    them together: a flight's rows go on the race's clock at `started_at + t - start_time_s`
    (Unix seconds). A pilot whose flights cannot be read (its files were deleted) comes with
    none."""
    del session
    record = race_record_named(manager.store.folder(session_id), number)
    if record is None:
        raise SessionError("not_found", f"no finished race {number} in this session")
    pilots = []
    for pilot in record["pilots"]:
        flights = []
        try:
            for flight_id in flights_in(read_index(manager.store, pilot["session"]), record):
                flights.append(read_flight(manager.store, pilot["session"], flight_id))
        except (StoreError, FlightNotFound):
            flights = []
        pilots.append({"session": pilot["session"], "name": pilot["name"], "flights": flights})
    return JSONResponse({"race": record, "pilots": pilots})
