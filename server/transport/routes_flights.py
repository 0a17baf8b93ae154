"""REST API for a session's flight recordings: the list, one flight as JSON, its states as CSV
and its path as a TUM trajectory.

The worker saves each flight under the session's folder (``server/sessions/flight_store.py``);
these routes read the files there, so a closed session's flights, and those of a session saved
before a restart, download as a live one's do. The session's token opens them (401 / 404 as
every session route).
"""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Response
from fastapi.responses import JSONResponse

from server.sessions import SessionError
from server.sessions.flight_store import FlightNotFound, read_flight, read_index
from server.simulation.flight_recording import states_csv, states_tum
from server.transport.deps import ManagerDep, SessionDep
from server.transport.schemas import FlightList, FlightRecordingBody, error_response

router = APIRouter(prefix="/api/sessions", tags=["flights"])

_ERRORS: dict[int | str, dict[str, Any]] = {
    401: error_response("no `Authorization: Bearer <token>` header"),
    404: error_response(
        "unknown session id, a token that does not open it, or no flight with this id"
    ),
}


_CSV: dict[int | str, dict[str, Any]] = {
    200: {
        "description": "the flight's states: a header line `t,x,y,z,vx,vy,vz,qx,qy,qz,qw,mode`, "
        "then one line per drone state (the JSON's state_columns and states)",
        "content": {"text/csv": {"schema": {"type": "string"}}},
    }
}


_TUM: dict[int | str, dict[str, Any]] = {
    200: {
        "description": "the drone's path, TUM format: a `#` comment line, then one line "
        "`t x y z qx qy qz qw` per drone state",
        "content": {"text/plain": {"schema": {"type": "string"}}},
    }
}


def _flight(manager, session_id: str, flight_id: str) -> dict:
    try:
        return read_flight(manager.store, session_id, flight_id)
    except FlightNotFound as exc:  # the session's answer, not the store's "no session"
        raise SessionError("not_found", str(exc)) from None


@router.get("/{session_id}/flights", response_model=FlightList, responses=_ERRORS)
def list_flights(session_id: str, session: SessionDep, manager: ManagerDep) -> JSONResponse:
    """The session's recorded flights, oldest first: id, start, duration, why it ended, the
    course's result when one was flown. A flight in progress appears as of the latest
    snapshot (`finished: false`)."""
    return JSONResponse({"flights": read_index(manager.store, session_id)})


@router.get(
    "/{session_id}/flights/{flight_id}.json",
    response_model=FlightRecordingBody,
    responses=_ERRORS,
)
def download_flight(
    session_id: str, flight_id: str, session: SessionDep, manager: ManagerDep
) -> JSONResponse:
    """One flight, whole: drone states (rows of `state_columns`), events, the pilot's
    commands, the course and its result (shared/PROTOCOL.md, "Flight recordings")."""
    return JSONResponse(_flight(manager, session_id, flight_id))


@router.get(
    "/{session_id}/flights/{flight_id}.csv",
    response_class=Response,
    responses={**_CSV, **_ERRORS},
)
def download_flight_csv(
    session_id: str, flight_id: str, session: SessionDep, manager: ManagerDep
) -> Response:
    """The flight's drone states as CSV (columns as the JSON's `state_columns`: t in
    simulation seconds, x y z metres and vx vy vz m/s in the world frame, qx qy qz qw the
    drone's attitude, mode)."""
    data = states_csv(_flight(manager, session_id, flight_id))
    return Response(
        data,
        media_type="text/csv",
        headers={
            "Content-Disposition": f'attachment; filename="{session_id}-flight-{flight_id}.csv"'
        },
    )


@router.get(
    "/{session_id}/flights/{flight_id}.tum",
    response_class=Response,
    responses={**_TUM, **_ERRORS},
)
def download_flight_tum(
    session_id: str, flight_id: str, session: SessionDep, manager: ManagerDep
) -> Response:
    """The drone's path as a TUM trajectory, T_world_drone: `t` in simulation seconds (0 at
    spawn), `x y z` the drone's centre in the world frame (metres), `qx qy qz qw` its attitude
    (unit quaternion, w >= 0). The world frame is that of the session's `trajectory.tum`, so
    evo draws both together: `evo_traj tum flight.tum trajectory.tum`."""
    data = states_tum(_flight(manager, session_id, flight_id))
    return Response(
        data,
        media_type="text/plain",
        headers={
            "Content-Disposition": f'attachment; filename="{session_id}-flight-{flight_id}.tum"'
        },
    )
