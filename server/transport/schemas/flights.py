"""A session's recorded flights: ``GET /api/sessions/{id}/flights`` and one flight's JSON."""

from __future__ import annotations

from pydantic import Field

from server.transport.schemas.common import WireModel


class FlightSummary(WireModel):
    """One recorded flight in ``GET /api/sessions/{id}/flights``."""

    id: str = Field(description="the flight's id within the session: 1, 2, ... in order")
    started_at: float = Field(description="when the flight opened, Unix seconds (server clock)")
    duration_s: float = Field(description="simulation time from its first entry to its last, s")
    finished: bool = Field(
        description="false: the flight was in progress when saved (it is saved with every "
        "snapshot and again when it ends)"
    )
    end: str | None = Field(
        description="why it ended: landed, faulted, course_finished, session_end; in_progress "
        "while it goes on"
    )
    states: int = Field(description="drone states recorded (rows of the CSV)")
    events: int = Field(description="drone events recorded")
    commands: int = Field(description="pilot commands recorded")
    has_course: bool = Field(description="a course was being flown (the JSON holds it)")
    result: dict | None = Field(
        description="the course's result as the course judge gave it (time_s, gates_passed, "
        "gates_missed, collisions, score, ...), null without one"
    )
    bytes: int = Field(description="size of the flight's JSON, bytes")


class FlightList(WireModel):
    """``GET /api/sessions/{id}/flights``: the session's saved flights, oldest first."""

    flights: list[FlightSummary] = Field(description="at most the server's flights_kept, newest")


class FlightEvent(WireModel):
    """A drone_event during the flight."""

    t: float = Field(description="simulation time, s")
    event: str = Field(description="drone_event.event")
    position: list[float] = Field(
        min_length=3, max_length=3, description="drone position, world frame, m"
    )
    message: str = Field(description="drone_event.message")
    command_id: int | None = Field(description="the command it concerns, if any")


class FlightCommand(WireModel):
    """A pilot command the drone accepted, with the fields it was sent with (target, pixel,
    seq, sticks, speed: those given, as in the protocol's `command`)."""

    t: float = Field(description="simulation time it arrived at, s")
    name: str = Field(description="command.name")
    id: int = Field(description="command.id")


class FlightRecordingBody(WireModel):
    """``GET /api/sessions/{id}/flights/{flight_id}.json``: one flight, whole."""

    format: str = Field(description="dronesim-flight/1")
    id: str = Field(description="the flight's id")
    started_at: float = Field(description="when it opened, Unix seconds (server clock)")
    start_time_s: float = Field(description="simulation time of its first entry, s")
    end_time_s: float = Field(description="simulation time of its last entry, s")
    duration_s: float = Field(description="end_time_s - start_time_s, s")
    finished: bool = Field(description="false while it was in progress when saved")
    end: str | None = Field(
        description="landed, faulted, course_finished, session_end, in_progress"
    )
    state_hz: float = Field(description="drone states per second (the server's drone_state_hz)")
    state_columns: list[str] = Field(
        description="the columns of each row of states: t (simulation time, s), x y z (drone "
        "centre, world frame, m), vx vy vz (velocity, world frame, m/s), qx qy qz qw (unit "
        "quaternion of T_world_drone's rotation, w >= 0), mode (drone_state.mode)"
    )
    states: list[list[float | str]] = Field(description="one row per drone state, in order")
    events: list[FlightEvent] = Field(description="drone events, in order")
    commands: list[FlightCommand] = Field(description="accepted pilot commands, in order")
    course: dict | None = Field(description="the course flown (as the course module gave it)")
    result: dict | None = Field(description="the course's result, when the course finished")
    truncated: bool = Field(
        description="the flight outlasted flight_max_s (or its event/command caps): later "
        "entries were not kept"
    )
