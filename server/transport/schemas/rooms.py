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
