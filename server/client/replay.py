"""Replay an RGB-D sequence to a server session over the WebSocket protocol, paced like a camera.

Frames are 'captured' on a fixed schedule; when the client already has ``max_in_flight`` frames
unanswered, the captured frame is dropped on the client side, as a phone would. The result says
whether the run completed: every frame sent was answered and the server closed after bye.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import websockets

from server import protocol as proto
from server.client.connection import NORMAL_CLOSE, Connection, MapCorrection, close_name
from server.datasets import RGBDDataset

log = logging.getLogger(__name__)

ANSWER_TIMEOUT_S = 30.0  # the longest wait for an answer (a frame's, or the last ones')
CLOSE_TIMEOUT_S = 10.0  # the longest wait for the server's close after bye


@dataclass
class ReplayStats:
    """What one replay saw. Latency: send to pose, milliseconds.

    ``failure`` says what ended the run early or left it incomplete (None: it completed);
    ``missing`` counts the frames sent and never answered."""

    sent: int = 0
    client_dropped: int = 0
    poses: list[dict] = field(default_factory=list)
    latencies_ms: list[float] = field(default_factory=list)
    errors: list[dict] = field(default_factory=list)
    map_points: int = 0
    welcome: dict | None = None
    drone_events: list[dict] = field(default_factory=list)
    corrections: list[MapCorrection] = field(default_factory=list)  # map_corrected received
    map_resets: int = 0  # map chunks with reset (a rebuilt map's preview)
    missing: int = 0
    invalid: list[str] = field(default_factory=list)  # server messages that broke the protocol
    close_code: int | None = None
    failure: str | None = None

    @property
    def answered(self) -> int:
        """Frames sent and answered (by a pose, their own or a later frame's, or an error)."""
        return self.sent - self.missing

    @property
    def completed(self) -> bool:
        return self.failure is None

    def describe(self) -> str:
        """One line for a log: counts, and what went wrong when it did."""
        line = f"{self.sent} frames sent, {self.answered} answered, {self.missing} missing"
        return line if self.completed else f"{line}; incomplete: {self.failure}"


async def replay(
    ws_url: str,
    token: str,
    dataset: RGBDDataset,
    fps: float = 15.0,
    max_frames: int | None = None,
    loop_sequence: bool = False,
    max_in_flight: int = 2,
    depth_format: str = "png",
    client_name: str = "replay",
    on_pose: Callable[[dict], None] | None = None,
    ssl=None,
    drop_when_busy: bool = True,
    preencode: bool = False,
    pilot: Callable[[dict], dict | None] | None = None,
) -> ReplayStats:
    """Stream ``dataset`` to the session at ``ws_url`` and collect what comes back.

    drop_when_busy: a frame captured while ``max_in_flight`` frames await answers is dropped
    (a camera); False waits for an answer instead, so that every frame is sent (tests).
    preencode: JPEG/PNG-encode every frame before streaming, so that the client's encoding time
    (a phone's own work) does not sit in the measured latency (benchmarks).
    pilot: sees every message from the server and may answer with a ``command`` to send.

    Returns partial statistics when the run ends early, with ``failure`` saying why; raises
    only when no conversation starts (refused connection: websockets.InvalidHandshake, OSError;
    no welcome: ClientError)."""
    stats = ReplayStats()
    K = dataset.intrinsics
    n = len(dataset) if max_frames is None else max_frames

    def frame_message(i: int) -> dict:
        frame = dataset[i % len(dataset)]
        return proto.make_frame(
            i,
            frame.timestamp,
            frame.colour,
            frame.depth,
            depth_format=depth_format,
            depth_scale=1000.0,
            # A phone's recording sends its own odometry, as the phone would live.
            T_device_camera=dataset.device_pose(frame.index),
        )

    def encode_all() -> dict[int, dict]:
        return {i: frame_message(i) for i in range(min(n, len(dataset)))}

    cache = await asyncio.to_thread(encode_all) if preencode else {}
    hello = proto.make_hello(
        client_name, (K.fx, K.fy, K.cx, K.cy), (K.width, K.height), depth_scale=1000.0
    )
    conn = await Connection.open(ws_url, token, hello, ssl=ssl, timeout=ANSWER_TIMEOUT_S)
    stats.welcome = conn.welcome

    async def on_message(msg: dict, latency_ms: float | None) -> None:
        kind = msg["type"]
        if kind == "pose":
            if latency_ms is not None:
                stats.latencies_ms.append(latency_ms)
            stats.poses.append(msg)
            if on_pose is not None:
                on_pose(msg)
        elif kind == "map_chunk":
            stats.map_points += msg["count"]
            stats.map_resets = conn.map_resets
        elif kind == "map_corrected":
            stats.corrections = list(conn.corrections)
        elif kind == "error":
            stats.errors.append(msg)
        elif kind == "drone_event":
            stats.drone_events.append(msg)
        if pilot is not None and (command := pilot(msg)) is not None:
            await conn.send(command)

    async def stream() -> str | None:
        """Send the frames on their schedule; -> why streaming stopped early, or None."""
        start = time.monotonic()
        for i in range(n):
            if not conn.receiving:
                return _ended(conn, stats)
            due = start + i / fps
            await asyncio.sleep(max(0.0, due - time.monotonic()))
            if not drop_when_busy and not await conn.wait_for_room(max_in_flight, ANSWER_TIMEOUT_S):
                if not conn.receiving:
                    return _ended(conn, stats)
                return f"no answer within {ANSWER_TIMEOUT_S:g} s to {max_in_flight} frames"
            if len(conn.in_flight) >= max_in_flight:
                stats.client_dropped += 1
                continue
            if not loop_sequence and i >= len(dataset):
                break
            # Encoding runs off the event loop: the loop may be a server's (the demo).
            message = cache.get(i % len(dataset))
            if message is None:
                message = await asyncio.to_thread(frame_message, i)
            await conn.send_frame({**message, "seq": i})
            stats.sent += 1
        return None

    conn.start(on_message)
    try:
        stats.failure = await stream()
        if stats.failure is None and not await conn.drain(ANSWER_TIMEOUT_S):
            stats.failure = (
                _ended(conn, stats)
                if not conn.receiving
                else f"no answer within {ANSWER_TIMEOUT_S:g} s to the last frames"
            )
        if conn.receiving:
            try:
                await conn.bye("done", CLOSE_TIMEOUT_S)
            except asyncio.TimeoutError:
                stats.failure = stats.failure or "no close from the server after bye"
    except websockets.ConnectionClosed:
        stats.failure = _ended(conn, stats)
    finally:
        await conn.close()
    stats.close_code = conn.close_code
    stats.missing = len(conn.in_flight)
    stats.invalid = list(conn.invalid)
    stats.failure = stats.failure or _failure(conn, stats)
    return stats


def _ended(conn: Connection, stats: ReplayStats) -> str:
    """Why the connection ended before the replay did."""
    if conn.failure is not None:
        return f"client failed: {conn.failure}"
    return f"the connection ended ({close_name(conn.close_code)}) after {stats.sent} frames"


def _failure(conn: Connection, stats: ReplayStats) -> str | None:
    """What makes a finished run incomplete, if anything (checked in this order)."""
    if conn.failure is not None:
        return f"client failed: {conn.failure}"
    if stats.close_code != NORMAL_CLOSE:
        return f"connection ended with {close_name(stats.close_code)}"
    if stats.missing:
        return f"{stats.missing} frames never answered"
    if stats.invalid:
        return f"{len(stats.invalid)} invalid server messages, first: {stats.invalid[0]}"
    return None


def latency_summary(stats: ReplayStats) -> dict:
    lat = np.array(stats.latencies_ms) if stats.latencies_ms else np.array([np.nan])
    return {
        "sent": stats.sent,
        "answered": stats.answered,
        "missing": stats.missing,
        "completed": stats.completed,
        "failure": stats.failure,
        "poses": len(stats.poses),
        "client_dropped": stats.client_dropped,
        "server_dropped": stats.poses[-1]["dropped"] if stats.poses else 0,
        "errors": len(stats.errors),
        "p50_ms": float(np.percentile(lat, 50)),
        "p95_ms": float(np.percentile(lat, 95)),
        "p99_ms": float(np.percentile(lat, 99)),
    }
