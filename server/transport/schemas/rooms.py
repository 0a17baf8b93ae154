"""Shared rooms: an invitation (``POST /api/sessions/{id}/invites``) and the room a session's
status names (``SessionStatus.shared_room``)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from server.transport.schemas.common import WireModel


class InviteCreated(WireModel):
    """``POST /api/sessions/{id}/invites`` answers 201 with this body."""

    join_token: str = Field(
        description="the invitation's secret (256 bits, URL-safe base64), shown only here; "
        "the server keeps only its SHA-256. A phone opens a session of its own in the room "
        'with `POST /api/sessions` `{"join": "<id>"}` and this token as `Authorization: '
        "Bearer`. It opens nothing else, and nothing once the room's session has ended"
    )
    join: str = Field(
        description="the room's session id: the `join` of the new session's body",
        pattern="^[0-9a-f]{16}$",
    )


class SharedRoom(WireModel):
    """The shared room a live session belongs to."""

    owner: str = Field(description="the id of the session whose room it is (that invited)")
    phones: list[str] = Field(
        description="the sessions that joined the room, in the order they joined (those that "
        "ended included)"
    )


class RaceStart(WireModel):
    """The body of ``POST /api/sessions/{id}/race``."""

    difficulty: Literal["easy", "medium", "hard"] = Field(
        "medium", description="the course's preset (PROTOCOL.md, Courses)"
    )
    seed: int | None = Field(
        None,
        ge=0,
        description="the course generator's seed (the same course from the same "
        "place); null: a random one",
    )
    countdown_s: float = Field(
        3.0, ge=0.0, le=30.0, description="seconds from now to the start, shown to every phone"
    )
    autopilot: bool = Field(
        False, description="every drone flies the course by itself (a demonstration)"
    )


class RaceStarted(WireModel):
    """``POST /api/sessions/{id}/race`` answers 201 with this body."""

    race: int = Field(description="which race of the room: 1, 2, ...")
    gates: int = Field(description="gates in the course")
    difficulty: str = Field(description="the course's preset")
    seed: int = Field(description="the course generator's seed")
    starts_in_s: float = Field(description="seconds from this answer to the start")


class RacePilot(WireModel):
    """One pilot's race, as the room's standings left it when the race finished."""

    session: str = Field(description="the pilot's session id")
    name: str = Field(description="the pilot's client name (its hello's)")
    passed: int = Field(description="gates flown through in order")
    missed: int = Field(description="gates left out")
    time_s: float = Field(description="simulation time from the start to its last gate, s")
    crashes: int = Field(description="crashes during the race (each restarted at the last gate)")
    finished: bool = Field(description="every gate passed or missed")
    rank: int = Field(description="1 for the fastest who finished, 2 for the next; 0: did not")


class RaceRecord(WireModel):
    """A finished race of a shared room."""

    number: int = Field(description="which race of the room's session: 1, 2, ...")
    difficulty: str = Field(description="the course's preset")
    seed: int = Field(description="the course generator's seed")
    gates: list[float] = Field(
        description="N x 7: each gate's centre, unit normal and ring radius, world frame, m"
    )
    started_at: float = Field(description="the end of the countdown, Unix seconds (server)")
    ended_at: float = Field(description="when the last pilot finished or gave up, Unix seconds")
    owner: str = Field(description="the room's session id")
    pilots: list[RacePilot] = Field(description="each pilot of the room at the finish")


class RaceBestEntry(WireModel):
    """A pilot's finished race in the room's best list."""

    pilot: str = Field(description="the pilot's client name")
    session: str = Field(description="the pilot's session id")
    race: int = Field(description="the race's number in its room's session")
    time_s: float = Field(description="simulation time from the start to the last gate, s")
    gates: int = Field(description="gates in the course")
    missed: int = Field(description="gates left out")
    crashes: int = Field(description="crashes during the race")
    difficulty: str = Field(description="the course's preset")
    seed: int = Field(description="the course generator's seed")
    finished_at: float = Field(description="when the race finished, Unix seconds")


class RaceList(WireModel):
    """``GET /api/sessions/{id}/races``: the races this session flew in, and its room's best."""

    races: list[RaceRecord] = Field(description="oldest first (the newest 100)")
    best: list[RaceBestEntry] = Field(
        description="the room's best list: at most 10, fewest gates missed first, then the "
        "fastest, then the earlier. It travels with the saved room: a session continuing "
        "in it starts from the earlier days' list"
    )


class RacePilotFlights(WireModel):
    """A pilot's recorded flights that overlap a race (FlightRecordingBody each)."""

    session: str = Field(description="the pilot's session id")
    name: str = Field(description="the pilot's client name")
    flights: list[dict] = Field(
        description="the pilot's flights open during the race, oldest first, whole "
        "(`GET .../flights/{flight_id}.json` bodies); a flight's `started_at` (Unix "
        "seconds) puts its rows on the race's clock: wall = started_at + t - start_time_s"
    )


class RaceFlights(WireModel):
    """``GET /api/sessions/{id}/races/{number}/flights``: every pilot's flights of one race, to
    replay them together."""

    race: RaceRecord = Field(description="the race")
    pilots: list[RacePilotFlights] = Field(description="in the race record's order")
