"""A viewer link's WebSocket, ``/ws/sessions/{id}/view?token=<viewer token>``: read-only.

A viewer gets a ``welcome`` with ``role: viewer``, then what the session showed before it came
(the map preview so far, the drone's ``spawned`` event, the latest pose and drone state), then
the session's ``pose``, ``map_chunk``, ``drone_state`` and ``drone_event`` messages live, as the
owner's socket does. It never takes the session over (its sockets are apart from the owner's,
``app.state.connections``) and may send nothing: every message it sends is answered with the
non-fatal error ``read_only`` and changes nothing. Its updates wait in a bounded queue of its
own (``viewer_outbox``), so a slow viewer loses its oldest updates (never a world's correction
or the map's restart) and never slows the owner or another viewer. A revoked link, or the
session's end, closes it (``unauthorized``, 4003).
"""

from __future__ import annotations

import asyncio
import logging

from fastapi import APIRouter, WebSocket, WebSocketDisconnect

from server import protocol as proto
from server.sessions import DroneUpdate, LiveSession, MapUpdate, PoseUpdate, RoomUpdate
from server.sessions.failures import SessionLog
from server.sessions.store import SESSION_ID
from server.sessions.web.viewers import ViewerSocket, merged_map
from server.transport.outbox import Outbox
from server.transport.websocket import _refuse, _send, update_messages

log = logging.getLogger(__name__)
router = APIRouter()

OUTBOX = 64  # updates waiting for one viewer; beyond this its oldest are dropped
_CHECK_S = 1.0  # how often a quiet viewer socket checks that its session is still live
_REFUSED = (
    "this is a viewer link: it watches the session and cannot send frames or commands; "
    "nothing was changed"
)


def viewer_outbox(size: int = OUTBOX) -> Outbox:
    """A viewer's queue: it needs only the newest pose and drone state of those waiting."""
    return Outbox(size, latest_only=(PoseUpdate, DroneUpdate, RoomUpdate))


class _Ending:
    """How other tasks end a viewer socket (event loop only): the first reason given wins."""

    def __init__(self) -> None:
        self.event = asyncio.Event()
        self.why: proto.ProtocolError | None = None

    def end(self, code: str, message: str) -> None:
        self.why = self.why or proto.ProtocolError(code, message)
        self.event.set()


def _session_for(app, session_id: str, token: str | None) -> tuple[LiveSession, str] | None:
    """The live session and viewer id that ``token`` opens, or None (the same for an unknown
    id, a closed session, a wrong or revoked token)."""
    if not SESSION_ID.fullmatch(session_id):
        return None
    session = app.state.manager.live_session(session_id)
    if session is None or session.closed:
        return None
    viewer_id = session.viewers.check(token)
    return None if viewer_id is None else (session, viewer_id)


@router.websocket("/ws/sessions/{session_id}/view")
async def viewer_socket(ws: WebSocket, session_id: str, token: str | None = None) -> None:
    app = ws.app
    await ws.accept()
    found = _session_for(app, session_id, token)
    if found is None:
        return await _refuse(
            ws,
            proto.ProtocolError(
                "unauthorized",
                "no live session with this id for this viewer token (revoked, or the session "
                "ended)",
            ),
        )
    session, viewer_id = found
    loop = asyncio.get_running_loop()
    outbox, ending = viewer_outbox(), _Ending()

    def deliver(item: object) -> None:  # any thread: only queues
        loop.call_soon_threadsafe(outbox.put, item)

    socket = ViewerSocket(viewer_id, deliver, ending.end)
    chunk_points = max(
        1, min(app.state.config.mapping.preview_points, proto.LIMITS["max_map_chunk_points"])
    )
    # Welcome and backlog go into the outbox before anything delivered from now on (those
    # arrive through call_soon_threadsafe, after this synchronous stretch).
    backlog = session.viewers.listen(socket)
    outbox.put(
        proto.make_welcome(
            session.id, max_message_bytes=app.state.settings.max_message_bytes, role="viewer"
        )
    )
    preview = merged_map([u for u in backlog if isinstance(u, MapUpdate)])
    for item in ([preview] if preview is not None else []) + [
        u for u in backlog if not isinstance(u, MapUpdate)
    ]:
        outbox.put(item)
    sender = asyncio.create_task(_send_updates(ws, outbox, chunk_points, session, ending))
    try:
        await _receive(ws, session, ending)
    except WebSocketDisconnect:
        pass
    finally:
        session.viewers.unlisten(socket)
        sender.cancel()
    if ending.why is not None:
        await _refuse(ws, ending.why)


async def _receive(ws: WebSocket, session: LiveSession, ending: _Ending) -> None:
    """Answer whatever the viewer sends with read_only, until it leaves or is ended; check
    every _CHECK_S that the session is still live."""
    refused = 0
    ended = asyncio.ensure_future(ending.event.wait())
    try:
        while True:
            receiving = asyncio.ensure_future(ws.receive())
            done, _ = await asyncio.wait(
                {receiving, ended}, timeout=_CHECK_S, return_when=asyncio.FIRST_COMPLETED
            )
            if receiving not in done:
                receiving.cancel()
                if ended in done:
                    return
                if session.closed:
                    ending.end("unauthorized", "the session was closed or deleted")
                    return
                continue
            received = receiving.result()
            if received["type"] == "websocket.disconnect":
                return
            refused += 1
            await _send(ws, _refusal(received.get("bytes")))
            if refused >= proto.LIMITS["max_consecutive_errors"]:
                await ws.close(code=proto.CLOSE_CODES["too_many_errors"], reason="too_many_errors")
                return
    finally:
        ended.cancel()


def _refusal(data: bytes | None) -> dict:
    """read_only, naming the refused frame's seq or command's id when they can be read."""
    seq = command_id = None
    try:
        message = proto.decode(data, direction=proto.CLIENT_TO_SERVER)
        seq = message.get("seq") if message["type"] == "frame" else None
        command_id = message.get("id") if message["type"] == "command" else None
    except proto.ProtocolError:
        pass
    return proto.make_error("read_only", _REFUSED, seq=seq, command_id=command_id)


async def _send_updates(
    ws: WebSocket, outbox: Outbox, chunk_points: int, session: LiveSession, ending: _Ending
) -> None:
    chunk = 0  # this socket's own chunk numbers: its backlog started them afresh
    try:
        while True:
            messages, chunk = update_messages(await outbox.get(), chunk_points, chunk)
            for message in messages:
                await _send(ws, message)
    except (WebSocketDisconnect, OSError, asyncio.CancelledError, RuntimeError):
        return  # the viewer left (Starlette raises RuntimeError on a closed socket)
    except Exception:  # a bug: say so to this viewer alone, the session goes on
        SessionLog(log, session.id).exception("sending to a viewer failed")
        ending.end("send_failed", "the server failed to send an update to this viewer")
