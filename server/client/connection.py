"""The one Python client of the protocol: a session's WebSocket from hello to bye.

Two layers. ``Socket`` sends and receives single messages, encoded and checked against
protocol.json, or raw data (for tests that send malformed input on purpose). ``Connection``
adds the client's side of the conversation: hello and welcome, frames within the window of
frames in flight, a receiver task that hands every server message to a callback, bye and the
server's close. ``create_session`` makes the session over REST first.

Replay (``replay``), the load tester (``loadtest``), the demo session and the tests all talk to
the server through this module.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import websockets

from server import protocol as proto
from server.client import rest
from server.errors import DroneSimError

log = logging.getLogger(__name__)

CLOSE_NAMES = {code: name for name, code in proto.CLOSE_CODES.items()}
NORMAL_CLOSE = 1000  # what the server closes with after bye


class ClientError(DroneSimError):
    """The server refused the conversation (no welcome, the session could not be made) or
    broke it. ``reply`` is the message that came instead of the expected one, if any."""

    def __init__(self, message: str, reply: dict | None = None) -> None:
        super().__init__(message)
        self.reply = reply


def close_name(code: int | None) -> str:
    """'close 4003 bad_token' style, 'no close frame' for None."""
    return f"close {code} {CLOSE_NAMES.get(code, '')}".strip() if code else "no close frame"


async def create_session(
    base_url: str, context: Any = None, timeout: float | None = None
) -> tuple[str, str]:
    """``POST /api/sessions`` -> (session id, token); raises ClientError when refused."""
    status, body = await asyncio.wait_for(
        asyncio.to_thread(rest.request, "POST", rest.sessions_url(base_url), None, context),
        timeout,
    )
    if status not in (200, 201) or not body:
        said = "unreachable" if status == 0 else f"HTTP {status}"
        raise ClientError(f"POST /api/sessions: {said}")
    return body["id"], body["token"]


async def dial(url: str, token: str | None, *, ssl: Any = None, **kwargs: Any) -> Any:
    """The raw WebSocket to ``url`` (``ws(s)://host:port/ws/sessions/{id}``) with the session's
    token (None: without one, as a stranger would try). Raises websockets.InvalidHandshake when
    the server refuses the upgrade."""
    query = "" if token is None else f"?token={token}"
    # No permessage-deflate, whatever the server offers: frames are JPEG and zlib already.
    kwargs.setdefault("compression", None)
    return await websockets.connect(f"{url}{query}", max_size=None, ssl=ssl, **kwargs)


class Socket:
    """One WebSocket to a session, message by message. Use ``Socket.connect``."""

    def __init__(self, ws: Any) -> None:
        self.ws = ws

    @classmethod
    async def connect(cls, url: str, token: str | None, *, ssl: Any = None, **kwargs: Any):
        """Open ``url`` with the session's token (see ``dial``)."""
        return cls(await dial(url, token, ssl=ssl, **kwargs))

    async def __aenter__(self):
        return self

    async def __aexit__(self, *exc_info: object) -> None:
        await self.close()

    async def send(self, message: dict) -> None:
        """Encode (strictly checked against protocol.json) and send one message."""
        await self.ws.send(proto.encode(message))

    async def send_raw(self, data: bytes | str) -> None:
        """Send anything, unchecked (a text frame for a str)."""
        await self.ws.send(data)

    async def receive_raw(self, timeout: float | None = None) -> bytes | str:
        """The next data from the server; raises websockets.ConnectionClosed, TimeoutError."""
        return await asyncio.wait_for(self.ws.recv(), timeout)

    async def receive(self, timeout: float | None = None) -> dict:
        """The next server message, checked; raises ProtocolError for an invalid one."""
        data = await self.receive_raw(timeout)
        return proto.decode(data, direction=proto.SERVER_TO_CLIENT)

    async def until_closed(self, timeout: float | None = None) -> list[dict]:
        """Every message the server still sends, up to its close (each within ``timeout``)."""
        messages = []
        try:
            while True:
                messages.append(await self.receive(timeout))
        except websockets.ConnectionClosed:
            return messages

    async def wait_closed(self, timeout: float | None = None) -> int | None:
        """Read (and discard) until the server closes; -> its close code."""
        try:
            while True:
                await self.receive_raw(timeout)
        except websockets.ConnectionClosed:
            return self.close_code

    async def ping(self, timeout: float | None = None) -> float:
        """A ping and its pong -> the round trip in seconds: proof that the server still holds
        this connection. Raises websockets.ConnectionClosed when it does not, TimeoutError."""
        t0 = time.monotonic()
        pong = await self.ws.ping()
        await asyncio.wait_for(pong, timeout)
        return time.monotonic() - t0

    @property
    def close_code(self) -> int | None:
        return self.ws.close_code

    @property
    def close_reason(self) -> str | None:
        return self.ws.close_reason

    async def close(self) -> None:
        await self.ws.close()

    def abort(self) -> None:
        """Drop the connection like a phone leaving the Wi-Fi: no close frame, no bye."""
        self.ws.transport.abort()


MessageHandler = Callable[[dict, "float | None"], "Awaitable[None] | None"]


@dataclass
class MapCorrection:
    """A ``map_corrected`` message as numbers: poses from ``from_seq`` on are in the corrected
    world; ``T_correction`` (4x4, metres) maps the old world into it; ``keyframes``: per id,
    (seq, corrected T_world_keyframe 4x4); ``map_resets_before``: reset map chunks received
    before it (the rebuilt map's preview comes after it)."""

    loops: int
    from_seq: int
    T_correction: np.ndarray
    keyframes: dict[int, tuple[int, np.ndarray]]
    refused: int
    map_resets_before: int = 0

    @classmethod
    def from_message(cls, message: dict, map_resets_before: int = 0) -> MapCorrection:
        T, keyframes = proto.decode_map_corrected(message)
        return cls(
            message["loops"],
            message["from_seq"],
            T,
            keyframes,
            message["refused"],
            map_resets_before,
        )


class Connection(Socket):
    """A session's conversation, client side.

    ``in_flight`` maps the seq of every frame sent and not yet answered to its monotonic send
    time. A pose answers its own frame and every earlier one (the server drops queued frames in
    favour of newer ones); an error naming a frame's seq answers that frame.

    ``corrections`` holds every ``map_corrected`` received (loop closures: ``MapCorrection``)
    and ``map_resets`` counts the map chunks with reset (a rebuilt map's preview), both kept
    by ``note`` (the receiver task calls it for every message).
    """

    def __init__(self, ws: Any) -> None:
        super().__init__(ws)
        self.welcome: dict | None = None
        self.in_flight: dict[int, float] = {}
        self.sent = 0  # frames sent
        self.invalid: list[str] = []  # server messages that broke the protocol
        self.failure: str | None = None  # what ended the receiver other than a close
        self._answered = asyncio.Event()  # set on every answer and when the receiver ends
        self._receiver: asyncio.Task | None = None
        self.corrections: list[MapCorrection] = []
        self.map_resets = 0

    @classmethod
    async def open(
        cls, url: str, token: str, hello: dict, *, ssl: Any = None, timeout: float = 30.0
    ) -> Connection:
        """Connect and say ``hello``; raises ClientError when no welcome comes back."""
        connection = await cls.connect(url, token, ssl=ssl)
        try:
            await connection.hello(hello, timeout)
        except BaseException:
            await connection.close()
            raise
        return connection

    async def hello(self, hello: dict, timeout: float | None = 30.0) -> dict:
        """Send ``hello`` -> the welcome; raises ClientError with the server's reply otherwise."""
        await self.send(hello)
        reply = await self.receive(timeout)
        if reply["type"] != "welcome":
            said = f" {reply['name']}: {reply['message']}" if reply["type"] == "error" else ""
            raise ClientError(f"expected welcome, got {reply['type']}{said}", reply)
        self.welcome = reply
        return reply

    # ---- frames and their answers --------------------------------------------------------------

    async def send_frame(self, frame: dict) -> float:
        """Send a frame message and count it in flight; -> the send time (monotonic seconds),
        taken after encoding, so that latencies measure the network and the server."""
        data = proto.encode(frame)
        sent_at = time.monotonic()
        self.in_flight[frame["seq"]] = sent_at
        await self.ws.send(data)
        self.sent += 1
        return sent_at

    def acknowledge(self, message: dict) -> float | None:
        """Take the frames ``message`` answers out of the window; -> for a pose of a frame sent
        here, its send-to-pose latency in milliseconds, else None."""
        kind, seq = message["type"], message.get("seq")
        if kind == "pose":
            seq = message["seq"]  # a pose always names its frame (protocol.json)
            sent_at = self.in_flight.get(seq)
            for s in [s for s in self.in_flight if s <= seq]:
                del self.in_flight[s]
            self._answered.set()
            return None if sent_at is None else (time.monotonic() - sent_at) * 1e3
        if kind == "error" and seq is not None:
            self.in_flight.pop(seq, None)
            self._answered.set()
        return None

    def note(self, message: dict) -> None:
        """Keep what the connection remembers of a server message: corrections, map resets."""
        kind = message["type"]
        if kind == "map_corrected":
            self.corrections.append(MapCorrection.from_message(message, self.map_resets))
        elif kind == "map_chunk" and message.get("reset"):
            self.map_resets += 1

    def start(self, on_message: MessageHandler | None = None) -> asyncio.Task:
        """Receive in a task until the connection ends: every server message updates the window,
        then goes to ``on_message(message, latency_ms)`` (which may be a coroutine function).
        An invalid message is recorded in ``invalid`` and skipped; a failing handler ends the
        task with ``failure`` set."""

        async def receive() -> None:
            try:
                async for data in self.ws:
                    try:
                        message = proto.decode(data, direction=proto.SERVER_TO_CLIENT)
                    except proto.ProtocolError as exc:
                        self.invalid.append(str(exc))
                        continue
                    latency_ms = self.acknowledge(message)
                    self.note(message)
                    if on_message is not None:
                        handled = on_message(message, latency_ms)
                        if handled is not None:
                            await handled
            except websockets.ConnectionClosed:
                pass  # the close code is on the socket
            except Exception as exc:  # a handler's bug must show in the result, not vanish
                self.failure = f"{type(exc).__name__}: {exc}"
                log.exception("message handler failed")
            finally:
                self._answered.set()

        self._receiver = asyncio.create_task(receive())
        return self._receiver

    @property
    def receiving(self) -> bool:
        """The receiver task runs (the connection is up)."""
        return self._receiver is not None and not self._receiver.done()

    async def wait_for_room(self, max_in_flight: int, timeout: float) -> bool:
        """Wait until fewer than ``max_in_flight`` frames await answers; False when ``timeout``
        (seconds) passes first or the connection ends."""
        return await self._wait(lambda: len(self.in_flight) < max_in_flight, timeout)

    async def drain(self, timeout: float) -> bool:
        """Wait until every frame sent is answered; False when ``timeout`` (seconds) passes
        first or the connection ends."""
        return await self._wait(lambda: not self.in_flight, timeout)

    async def _wait(self, done: Callable[[], bool], timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while not done():
            left = deadline - time.monotonic()
            if left <= 0 or not self.receiving:
                return False
            self._answered.clear()
            try:
                await asyncio.wait_for(self._answered.wait(), left)
            except asyncio.TimeoutError:
                return done()
        return True

    async def bye(self, reason: str | None = None, timeout: float = 10.0) -> int | None:
        """Say bye (while the connection is up) and wait for the server's close; -> its close
        code (1000 after a bye). Raises TimeoutError when the server does not close."""
        # Without a receiver task (a caller reading replies itself) the bye still goes out:
        # else the server would close only at its idle timeout (30 s).
        if self.receiving or self._receiver is None:
            try:
                await self.send(proto.make_bye(reason))
            except websockets.ConnectionClosed:
                pass
        if self._receiver is not None:
            await asyncio.wait_for(asyncio.shield(self._receiver), timeout)
        else:
            await self.wait_closed(timeout)
        return self.close_code

    async def close(self) -> None:
        await super().close()
        if self._receiver is not None:
            self._receiver.cancel()
