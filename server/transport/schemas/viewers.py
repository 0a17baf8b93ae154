"""Viewer links: ``POST`` and ``GET /api/sessions/{id}/viewers``."""

from __future__ import annotations

from pydantic import Field

from server.transport.schemas.common import WireModel


class ViewerCreated(WireModel):
    """``POST /api/sessions/{id}/viewers`` answers 201 with this body."""

    viewer_id: str = Field(description="names the viewer link (8 hex digits), for DELETE")
    viewer_token: str = Field(
        description="the viewer link's secret (256 bits, URL-safe base64), shown only here; "
        "the server keeps only its SHA-256. It opens the read-only socket and nothing else"
    )
    url: str = Field(
        description="the phone page opened as a viewer: `http(s)://host:port/#watch=<id>&token="
        "<viewer_token>` (in the fragment, which browsers never send to a server)"
    )
    websocket: str = Field(
        description="the viewer socket's URL without the token (`/ws/sessions/{id}/view`): "
        "append `?token=<viewer_token>`"
    )


class ViewerList(WireModel):
    """``GET /api/sessions/{id}/viewers``: the session's viewer links."""

    viewers: list[str] = Field(description="viewer_id of every link not revoked")
