"""REST API for viewer links: the owner (the session's token) hands out read-only links to
watch a live session, lists them and revokes them. The socket itself is
``server/transport/viewer_socket.py``."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Request, Response, status
from fastapi.responses import JSONResponse

from server.sessions import LiveSession, SessionError
from server.transport.deps import SessionDep, SettingsDep
from server.transport.schemas import ViewerCreated, ViewerList, error_response

router = APIRouter(prefix="/api/sessions", tags=["viewers"])

_ERRORS: dict[int | str, dict[str, Any]] = {
    401: error_response("no `Authorization: Bearer <token>` header"),
    404: error_response(
        "unknown session id, a token that does not open it, or (DELETE) no such viewer link"
    ),
}


def _live(session: LiveSession | dict) -> LiveSession:
    if not isinstance(session, LiveSession) or session.closed:
        raise SessionError(
            "session_closed", "this session is closed: only a live one can be watched"
        )
    return session


@router.post(
    "/{session_id}/viewers",
    status_code=status.HTTP_201_CREATED,
    response_model=ViewerCreated,
    responses=_ERRORS
    | {
        409: error_response(
            "`session_closed`: the session is closed; `too_many_viewers`: it has the server's "
            "max_viewers links already"
        )
    },
)
def create_viewer(
    request: Request, session_id: str, session: SessionDep, settings: SettingsDep
) -> JSONResponse:
    """A read-only link to watch this live session: **201** with `{viewer_id, viewer_token,
    url, websocket}`. Whoever has `url` (or the token) sees the map, the camera and the drone
    live and can change nothing; the owner's socket is never taken over."""
    viewer_id, token = _live(session).viewers.issue(settings.max_viewers)
    secure = request.url.scheme == "https"
    netloc = request.url.netloc
    body = {
        "viewer_id": viewer_id,
        "viewer_token": token,
        "url": f"{'https' if secure else 'http'}://{netloc}/#watch={session_id}&token={token}",
        "websocket": f"{'wss' if secure else 'ws'}://{netloc}/ws/sessions/{session_id}/view",
    }
    return JSONResponse(body, status_code=status.HTTP_201_CREATED)


@router.get("/{session_id}/viewers", response_model=ViewerList, responses=_ERRORS)
def list_viewers(session: SessionDep) -> JSONResponse:
    """The viewer links of the session that are not revoked ([] for a closed session)."""
    ids = session.viewers.ids() if isinstance(session, LiveSession) else []
    return JSONResponse({"viewers": ids})


@router.delete(
    "/{session_id}/viewers/{viewer_id}",
    status_code=status.HTTP_204_NO_CONTENT,
    response_class=Response,
    responses=_ERRORS,
)
async def revoke_viewer(viewer_id: str, session: SessionDep) -> Response:
    """Revoke a viewer link: **204**; its open sockets get `unauthorized` and close 4003, and
    the token opens nothing any more."""
    ending = session.viewers.revoke(viewer_id) if isinstance(session, LiveSession) else None
    if ending is None:
        raise SessionError("not_found", f"no viewer link {viewer_id!r} in this session")
    for socket in ending:  # this coroutine runs on the event loop, as the sockets do
        socket.end("unauthorized", "this viewer link was revoked by the session's owner")
    return Response(status_code=status.HTTP_204_NO_CONTENT)
