"""Creating a session (``POST /api/sessions``) and its course results
(``GET /api/sessions/{id}/course/best``)."""

from __future__ import annotations

from pydantic import Field, model_validator

from server.transport.schemas.common import WireModel


class SessionCreate(WireModel):
    """The optional body of ``POST /api/sessions``."""

    room: str | None = Field(
        None,
        description="continue in the room a closed session saved: that session's id. The "
        "request's `Authorization: Bearer <token>` must be that session's token. The new "
        "session relocalises its first frames in the room and tracks in its world frame; the "
        "map and the drone's map start as the room's",
        pattern="^[0-9a-f]{16}$",
    )
    loop_closure: bool | None = Field(
        None,
        description="close loops in this session: when the camera comes back to a place it "
        "saw, the keyframes are corrected, the map re-fused and `map_corrected` sent (PROTOCOL.md, "
        '"Loop closure"; costs the server ~0.1 s of CPU per keyframe and a re-fuse per loop). '
        "null: the server's setting (`registration.loops.live`). Not in a session continuing "
        "in a room",
    )
    join: str | None = Field(
        None,
        description="join the room of this live session (its id): the request's "
        "`Authorization: Bearer <token>` must be a join token of that room (`POST /api/"
        "sessions/{id}/invites`). The new session has its own tracker, drone and token; it "
        "places its first frames in the room as it stood at the join by place recognition "
        "(no pose guess), then tracks in the room's world frame and fuses into the room's map",
        pattern="^[0-9a-f]{16}$",
    )

    @model_validator(mode="after")
    def _one_room(self) -> SessionCreate:
        if self.room is not None and self.join is not None:
            raise ValueError("give `room` (a saved room) or `join` (a live one), not both")
        return self


class SessionCreated(WireModel):
    """``POST /api/sessions`` answers 201 with this body."""

    id: str = Field(
        description="the session's id: 16 lowercase hex digits; {id} of every session URL",
        pattern="^[0-9a-f]{16}$",
    )
    token: str = Field(
        description="the session's secret (256 bits, URL-safe base64), shown only in this "
        "answer: every other call needs it, as `Authorization: Bearer <token>` on REST and "
        "as `?token=` on the WebSocket. The server keeps only its SHA-256",
    )
    websocket: str = Field(
        description="URL of the session's WebSocket, ws:// or wss:// as the request came in "
        "(`/ws/sessions/{id}`), WITHOUT the token: append `?token=<token>` to connect",
    )
    room: str | None = Field(
        None, description="the room this session continues in (a session id), or null"
    )
    loop_closure: bool = Field(
        False, description="loop closure runs in this session (asked for, or the server's setting)"
    )
    join: str | None = Field(None, description="the live room this session joined, or null")


class CourseResult(WireModel):
    """One finished course run (PROTOCOL.md, "Courses")."""

    score: int = Field(description="the run's score (the course message's formula), >= 0")
    time_s: float = Field(description="simulation time from the start to the last gate, s")
    par_s: float = Field(description="the course's own route's time to its last gate, s")
    gates: int = Field(description="gates in the course")
    passed: int = Field(description="gates flown through in order")
    missed: int = Field(description="gates left out")
    bumps: int = Field(description="collision events during the run")
    crashes: int = Field(description="crash events during the run")
    difficulty: str = Field(description="easy, medium, hard, or custom")
    seed: int = Field(description="the course generator's seed")
    autopilot: bool = Field(description="the planner flew it (a demonstration), not the pilot")
    finished_at: float = Field(description="when it finished, Unix seconds (the server's clock)")


class CourseBest(WireModel):
    """``GET /api/sessions/{id}/course/best``: the session's best finished runs."""

    results: list[CourseResult] = Field(
        description="at most 10, highest score first (equal scores: the faster, then the "
        "earlier); kept in the session's files, so they outlast restarts"
    )
