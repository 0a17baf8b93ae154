"""The session WebSocket: route the client's messages, hand frames to the session, send poses
back.

This module knows the protocol and asyncio. It reads a frame's type only (``proto.peek``): the
frame goes on to the session's worker (a process of its own) as the bytes that arrived, and the
worker decodes, validates, orders and registers it, so one slow session never stalls the event
loop or another session; a frame the worker refuses comes back as a ``FrameRefused`` update,
answered here like a bad message. Other messages are decoded and validated here.
Which socket holds a session, and how other tasks end it, is ``connections.py``'s.
"""

from __future__ import annotations

import asyncio
import logging
import time

from fastapi import APIRouter, WebSocket, WebSocketDisconnect
from starlette.websockets import WebSocketState

from server import protocol as proto
from server.sessions import (
    CommandRefused,
    DroneNotice,
    DroneUpdate,
    FrameRefused,
    LiveSession,
    MapCorrected,
    MapUpdate,
    PoseUpdate,
    RoomUpdate,
    SessionError,
    SessionFailed,
    SessionTakenOver,
)
from server.sessions.failures import SessionLog
from server.transport.connections import RELEASE_WAIT_S, Connection
from server.transport.outbox import Outbox

log = logging.getLogger(__name__)
router = APIRouter()

# Session errors as the protocol names them.
_SESSION_CODES = {
    "no_hello": "unexpected_message",
    "bad_sequence": "bad_sequence",
    "intrinsics_changed": "bad_intrinsics",
    "session_closed": "unauthorized",
    "session_failed": "session_failed",
    # A session in a room refuses a camera other than the room's (or a room it cannot read).
    "room_unusable": "bad_intrinsics",
}


def _refusal(code: str, message: str, seq: int | None, counted: bool = True) -> proto.ProtocolError:
    """What the client hears when its session refuses a message, the one way for both roads
    a refusal takes from the worker: raised by a call (a SessionError's code), or published for
    a frame (a FrameRefused's code: a session's, or a protocol error's own name). A code the
    protocol has no name for is internal_error."""
    name = _SESSION_CODES.get(code, code)
    if name not in proto.ERRORS:
        name = "internal_error"
    return proto.ProtocolError(name, message, seq=seq, counted=counted)


# Updates waiting for a slow client; beyond this the oldest that may be lost are dropped
# (server/transport/outbox.py); drone states are coalesced, only the newest waits.
_OUTBOX = 256


async def _send(ws: WebSocket, message: dict) -> None:
    await ws.send_bytes(proto.encode(message))


async def _refuse(ws: WebSocket, error: proto.ProtocolError) -> None:
    try:
        await _send(ws, error.to_message())
        await ws.close(code=error.close_code or 1000, reason=error.code)
    except (RuntimeError, OSError, WebSocketDisconnect):
        pass


@router.websocket("/ws/sessions/{session_id}")
async def session_socket(ws: WebSocket, session_id: str, token: str | None = None) -> None:
    app = ws.app
    manager, settings = app.state.manager, app.state.settings
    connections: dict[str, Connection] = app.state.connections
    await ws.accept()
    try:
        # Off the event loop: with Ray, an id this process does not hold is looked up on the
        # cluster (up to seconds), and every other socket would wait for it.
        session = await asyncio.to_thread(manager.authorize, session_id, token)
    except SessionError as exc:
        return await _refuse(ws, proto.ProtocolError("unauthorized", str(exc)))
    if not isinstance(session, LiveSession):
        return await _refuse(ws, proto.ProtocolError("unauthorized", "this session is closed"))
    # The newest socket wins: a phone whose Wi-Fi dropped silently comes back on a new socket
    # while the server still holds the old one (until idle_timeout_s), and the token proves it
    # is the owner. The old socket is told why, so that a second tab stops instead of fighting.
    while (previous := connections.get(session_id)) is not None:
        previous.end(
            "session_taken_over",
            "a newer connection with this session's token took the session over",
        )
        try:
            await asyncio.wait_for(previous.released.wait(), RELEASE_WAIT_S)
        except asyncio.TimeoutError:
            await ws.close(code=proto.CLOSE_CODES["session_in_use"], reason="session_in_use")
            return
    connection = connections[session_id] = Connection()
    loop = asyncio.get_running_loop()
    outbox = Outbox(_OUTBOX, latest_only=(DroneUpdate, RoomUpdate))

    def deliver(item) -> None:  # any thread
        loop.call_soon_threadsafe(outbox.put, item)

    errors = _ErrorRun(proto.LIMITS["max_consecutive_errors"])
    # A larger preview (PREVIEW_POINTS) goes out in several chunks: one over the limit would be
    # refused by the codec.
    chunk_points = max(
        1, min(app.state.config.mapping.preview_points, proto.LIMITS["max_map_chunk_points"])
    )
    sender = asyncio.create_task(
        _send_updates(ws, outbox, chunk_points, session, connection, errors)
    )
    sender.add_done_callback(lambda task: _sender_ended(task, session, connection))
    try:
        await _receive(ws, session, deliver, settings.max_message_bytes, outbox, connection, errors)
    except WebSocketDisconnect:
        pass
    finally:
        session.on_update = None
        if connections.get(session_id) is connection:
            del connections[session_id]
        # Released before the client is told why: telling a phone gone silent can block on its
        # full socket buffer, and the newer socket must not wait for that.
        connection.released.set()
        sender.cancel()
    if connection.why is not None:
        await _refuse(ws, connection.why)


class _ErrorRun:
    """Non-fatal errors in a row; ``limit`` of them close the socket (too_many_errors). A pose,
    or any other message handled, ends the run. Event-loop thread only: the receiving task
    counts the client's bad messages, the sending task the frames the worker refused."""

    def __init__(self, limit: int) -> None:
        self.limit, self.count = limit, 0

    def reset(self) -> None:
        self.count = 0

    def add(self) -> bool:
        """Count one more; True when the run reached the limit."""
        self.count += 1
        return self.count >= self.limit


def _send_failed(session: LiveSession, connection: Connection) -> None:
    """Sending to this socket failed on a bug (logged by the caller): count it and end the
    connection with its documented code (send_failed, 4011); the session goes on, and the
    client's reconnect gets a fresh sender."""
    session.sends_failed += 1
    connection.end(
        "send_failed", "the server failed to send an update on this connection; reconnect"
    )


def _sender_ended(task: asyncio.Task, session: LiveSession, connection: Connection) -> None:
    """The sender task's end is observed: one that raised (past _send_updates' own guard)
    must not leave the client waiting for poses that will never come."""
    exc = None if task.cancelled() else task.exception()
    if exc is None:
        return
    SessionLog(log, session.id).error("the sender task died", exc_info=(type(exc), exc, None))
    _send_failed(session, connection)


def _closed(ws: WebSocket) -> bool:
    return WebSocketState.DISCONNECTED in (ws.client_state, ws.application_state)


def update_messages(
    item: dict | MapUpdate | MapCorrected | DroneUpdate | DroneNotice | PoseUpdate,
    chunk_points: int,
    chunk: int,
) -> tuple[list[dict], int]:
    """The messages one of a session's updates goes out as, to its owner or a viewer: a map
    update as chunks of at most ``chunk_points`` points numbered from ``chunk`` on (one even
    when it has no points: a rebuilt map's first, with reset, or the news of its surface); and
    the next chunk number."""
    if isinstance(item, dict):
        return [item], chunk
    if isinstance(item, MapUpdate):
        starts = range(
            0, max(len(item.points), 1 if item.reset or item.surface else 0), chunk_points
        )
        chunks = [
            proto.make_map_chunk(
                item.points[i : i + chunk_points],
                item.colours[i : i + chunk_points],
                chunk + k,
                total_points=item.total_points,
                reset=True if item.reset and k == 0 else None,
                surface=item.surface,
            )
            for k, i in enumerate(starts)
        ]
        return chunks, chunk + len(chunks)
    if isinstance(item, MapCorrected):
        corrected = proto.make_map_corrected(
            item.loops, item.from_seq, item.T_correction, item.keyframes, item.refused
        )
        return [corrected], chunk
    if isinstance(item, DroneUpdate):
        return [_drone_state(item)], chunk
    if isinstance(item, RoomUpdate):
        room = proto.make_room(
            item.names,
            item.you,
            item.placed,
            item.modes,
            item.drones,
            item.cameras,
            item.race,
            item.routes,
        )
        return [room], chunk
    if isinstance(item, DroneNotice):
        event = proto.make_drone_event(
            item.event, item.timestamp, item.position, item.message, item.command_id
        )
        return [event], chunk
    return [_pose(item)], chunk


async def _send_updates(
    ws: WebSocket,
    outbox: Outbox,
    chunk_points: int,
    session: LiveSession,
    connection: Connection,
    errors: _ErrorRun,
) -> None:
    chunk = 0
    try:
        while True:
            item = await outbox.get()
            if isinstance(item, FrameRefused):  # answered like a bad message, and counted
                error = _refusal(item.code, item.message, item.seq, item.counted)
                if error.fatal:  # the socket's handler tells the client and closes
                    connection.end_with(error)
                    return
                if await _report(ws, error, errors):
                    return
                continue
            if isinstance(item, SessionTakenOver):  # by a socket on another front-end
                connection.end("session_taken_over", item.message)
                return
            if isinstance(item, SessionFailed):
                kept = "saved" if item.saved else "kept as of its last snapshot"
                connection.end(
                    "session_failed",
                    f"{item.message}; the session is closed and {kept}, downloadable with its "
                    "token",
                )
                return
            if isinstance(item, PoseUpdate):
                errors.reset()
            messages, chunk = update_messages(item, chunk_points, chunk)
            for message in messages:
                await _send(ws, message)
    except (WebSocketDisconnect, OSError, asyncio.CancelledError):
        return
    except Exception as exc:  # a bug in sending must not leave the client waiting on a dead socket
        if isinstance(exc, RuntimeError) and _closed(ws):
            return  # Starlette's answer to a send on a socket that has closed
        SessionLog(log, session.id).exception("sending an update failed")
        _send_failed(session, connection)


def _pose(p: PoseUpdate) -> dict:
    return proto.make_pose(
        p.seq,
        p.timestamp,
        p.T_world_camera,
        p.state,
        p.inliers,
        p.timings_ms,
        p.dropped,
        p.keyframe,
        p.failures,
        p.recovery,
    )


async def _close_after_answers(ws: WebSocket, session: LiveSession, outbox: Outbox) -> None:
    """After a bye: answer the frames in flight (bounded), then close normally."""
    await asyncio.to_thread(session.drain, 5.0)
    deadline = time.monotonic() + 2.0
    while not outbox.empty() and time.monotonic() < deadline:
        await asyncio.sleep(0.01)
    if _closed(ws):
        return  # the client left meanwhile (a send found its socket gone): nothing to close
    try:
        await ws.close(code=1000, reason="bye")
    except (RuntimeError, OSError):
        if not _closed(ws):
            raise
        # Starlette's answer when the socket closed between the check and the close frame


_COMMAND_FIELDS = tuple(
    f["name"] for f in proto.MESSAGES["command"]["fields"] if f["name"] not in ("id", "name")
)


def _drone_state(s: DroneUpdate) -> dict:
    return proto.make_drone_state(
        s.timestamp,
        s.T_world_drone,
        s.velocity,
        s.mode,
        s.command_id,
        T_camera_drone=s.T_camera_drone,
        camera_seq=s.camera_seq,
        clearance=s.clearance,
        target=s.target,
        route=s.route,
        flight_mode=s.flight_mode,
        attitude=s.attitude,
        damage=s.damage,
    )


async def _receive(
    ws: WebSocket,
    session: LiveSession,
    deliver,
    max_bytes: int,
    outbox: Outbox,
    connection: Connection,
    errors: _ErrorRun,
) -> None:
    """Handle the client's messages until it leaves, is closed, or ``connection`` is ended."""
    order = proto.ClientOrder()
    idle_s = proto.LIMITS["idle_timeout_s"]
    ending = asyncio.ensure_future(connection.ending.wait())
    try:
        while True:
            receiving = asyncio.ensure_future(ws.receive())
            done, _ = await asyncio.wait(
                {receiving, ending}, timeout=idle_s, return_when=asyncio.FIRST_COMPLETED
            )
            if receiving not in done:
                receiving.cancel()
                if ending not in done:
                    await ws.close(code=proto.CLOSE_CODES["idle_timeout"], reason="idle_timeout")
                return
            received = receiving.result()
            if received["type"] == "websocket.disconnect":
                return
            data = received.get("bytes")
            if data is None:
                data = (received.get("text") or "").encode()  # text frames are not msgpack
            closed = False
            peeked: proto.Peek | None = None
            message: dict = {}
            try:
                peeked = proto.peek(data, max_bytes=max_bytes)
                if peeked.kind == "frame":  # forwarded unread; a frame's run ends with its pose
                    order.check("frame")
                    session.submit(data)
                else:
                    message = proto.decode(
                        data, direction=proto.CLIENT_TO_SERVER, max_bytes=max_bytes
                    )
                    order.check(message["type"])
                    await _handle(ws, session, message, deliver)
                    errors.reset()
            except CommandRefused as exc:  # an answer to the pilot, not a client error in a row
                refusal = proto.make_error(
                    exc.code, str(exc), command_id=message["id"], nearest=exc.nearest
                )
                await _send(ws, refusal)
            except SessionError as exc:  # the session refused it, or its worker is gone
                error = _refusal(exc.code, str(exc), None if peeked is None else peeked.seq)
                closed = await _report(ws, error, errors)
            except proto.ProtocolError as exc:
                closed = await _report(ws, exc, errors)
            except (WebSocketDisconnect, OSError):
                raise
            except Exception:  # a bug on one message: say so with a documented code, keep going
                SessionLog(log, session.id).exception("failed on a client message")
                error = proto.ProtocolError(
                    "internal_error",
                    "the server failed on this message",
                    seq=None if peeked is None else peeked.seq,
                )
                closed = await _report(ws, error, errors)
            if closed:
                return
            if order.closed:
                await _close_after_answers(ws, session, outbox)
                return
    finally:
        ending.cancel()


async def _report(ws: WebSocket, error: proto.ProtocolError, errors: _ErrorRun) -> bool:
    """Send the error; close on a fatal one or too many in a row. True when the socket was
    closed."""
    if error.fatal:
        await _refuse(ws, error)
        return True
    await _send(ws, error.to_message())
    if error.counted and errors.add():
        await ws.close(code=proto.CLOSE_CODES["too_many_errors"], reason="too_many_errors")
        return True
    return False


async def _handle(ws: WebSocket, session: LiveSession, message: dict, deliver) -> None:
    """A decoded, validated message other than a frame, in its place in the client's order."""
    kind = message["type"]
    if kind == "hello":
        await asyncio.to_thread(session.configure, message)
        session.start(deliver)
        await _send(
            ws,
            proto.make_welcome(
                session.id,
                max_message_bytes=ws.app.state.settings.max_message_bytes,
                queued_frames=proto.queued_frames(message),
            ),
        )
    elif kind == "command":
        # Every field the protocol lists for a command (absent ones as None); others ignored.
        fields = {k: message.get(k) for k in _COMMAND_FIELDS}
        await asyncio.to_thread(session.command, message["name"], message["id"], **fields)
