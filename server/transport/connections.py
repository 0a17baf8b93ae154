"""The one open WebSocket of each session, as other tasks see it: the route that deletes a
session, a newer socket with the same token and the server's shutdown end it (``Connection``,
``end_connection``, ``end_all_connections``), and wait until it has let go of the session.

``app.state.connections`` maps a session id to its ``Connection``; the socket's handler
(``server/transport/websocket.py``) adds and removes it. Event-loop thread only.
"""

from __future__ import annotations

import asyncio
from dataclasses import dataclass, field

from server import protocol as proto

RELEASE_WAIT_S = 5.0  # for the previous socket of a session to let go


@dataclass
class Connection:
    """The one open WebSocket of a session, as other tasks see it: they may end it (``end``),
    and wait until it has let go of the session (``released``)."""

    ending: asyncio.Event = field(default_factory=asyncio.Event)
    why: proto.ProtocolError | None = None  # what the client is told, then closed with
    released: asyncio.Event = field(default_factory=asyncio.Event)

    def end(self, code: str, message: str) -> None:
        """Event-loop thread only. The first reason given is the one the client hears."""
        self.end_with(proto.ProtocolError(code, message))

    def end_with(self, error: proto.ProtocolError) -> None:
        """As ``end``, with a fatal error as it stands (a refused frame's, with its seq)."""
        self.why = self.why or error
        self.ending.set()


def end_connection(app, session_id: str, code: str, message: str) -> None:
    """End a session's open socket, if it has one, with a fatal protocol error (event loop)."""
    connection = app.state.connections.get(session_id)
    if connection is not None:
        connection.end(code, message)


async def end_all_connections(app) -> None:
    """Tell every session's socket that the server is stopping and close it with the documented
    code; returns once all have let go of their sessions, or after a few seconds."""
    connections: dict[str, Connection] = app.state.connections
    waiting = list(connections.values())
    for connection in waiting:
        connection.end(
            "server_shutdown",
            "the server is stopping; this session is saved and "
            "closed, its map and trajectory stay downloadable with its token",
        )
    if waiting:
        released = [asyncio.ensure_future(c.released.wait()) for c in waiting]
        _, stuck = await asyncio.wait(released, timeout=RELEASE_WAIT_S)
        for future in stuck:
            future.cancel()
        await asyncio.sleep(0.1)  # let the handlers send their error and close frames
