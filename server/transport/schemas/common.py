"""The base of every body, and the error body every route answers with."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field


class WireModel(BaseModel):
    """The base of every REST body: a client must ignore the fields it does not know (``extra``
    allowed), as later versions may add some."""

    model_config = ConfigDict(extra="allow")


class ErrorDetail(WireModel):
    code: str = Field(
        description="unauthorized (401: no token), not_found (404: unknown id or wrong token, "
        "the same answer), rate_limited (429, with a Retry-After header in seconds), "
        "server_full (503: the server holds its maximum of live sessions), map_unavailable "
        "(409: no map surface fused yet), room_unavailable (409: the session named as a room "
        "saved none, or is still live; a live room to join has mapped nothing yet; a phone "
        "that joined a room asked to invite), room_full (409: the live room to join holds "
        "max_room_phones phones), race_unavailable (409: no course for the race can be laid "
        "where the owner's drone is), session_failed (400: the session's worker died "
        "during the request), session_closed (409: a viewer link asked of a closed session), "
        "too_many_viewers (409: the session has max_viewers links)"
    )
    message: str = Field(description="human-readable explanation")


class ErrorBody(WireModel):
    """Every REST error (4xx/5xx) carries this body."""

    error: ErrorDetail


def error_response(description: str) -> dict:
    """A route's documented error answer (FastAPI ``responses`` entry): ErrorBody, and when."""
    return {"model": ErrorBody, "description": description}
