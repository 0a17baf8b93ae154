"""Replay an RGB-D sequence to a server session over the WebSocket protocol, paced like a camera.

Frames are 'captured' on a fixed schedule; when the client already has ``max_in_flight`` frames
unanswered, the captured frame is dropped on the client side, as a phone would.
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
from server.datasets import RGBDDataset

log = logging.getLogger(__name__)


@dataclass
class ReplayStats:
    """What one replay saw. Latency: send to pose, milliseconds."""

    sent: int = 0
    client_dropped: int = 0
    poses: list[dict] = field(default_factory=list)
    latencies_ms: list[float] = field(default_factory=list)
    errors: list[dict] = field(default_factory=list)
    map_points: int = 0
    welcome: dict | None = None
    drone_events: list[dict] = field(default_factory=list)


async def await_answers(
    in_flight: dict,
    answered: asyncio.Event,
    deadline: float,
    gone: Callable[[], bool] = lambda: False,
) -> None:
    """Wait until no frame is in flight (``answered`` is set on each answer), the monotonic
    ``deadline`` passes, or ``gone()`` says the connection ended."""
    while in_flight and not gone() and time.monotonic() < deadline:
        answered.clear()
        try:
            await asyncio.wait_for(answered.wait(), max(0.01, deadline - time.monotonic()))
        except asyncio.TimeoutError:
            return


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
    pilot: sees every message from the server and may answer with a ``command`` to send."""
    stats = ReplayStats()
    K = dataset.intrinsics
    n = len(dataset) if max_frames is None else max_frames
    in_flight: dict[int, float] = {}

    def frame_message(i: int) -> dict:
        frame = dataset[i % len(dataset)]
        return proto.make_frame(
            i,
            frame.timestamp,
            frame.colour,
            frame.depth,
            depth_format=depth_format,
            depth_scale=1000.0,
        )

    def encode_all() -> dict[int, dict]:
        return {i: frame_message(i) for i in range(min(n, len(dataset)))}

    cache = await asyncio.to_thread(encode_all) if preencode else {}
    answered = asyncio.Event()
    async with websockets.connect(f"{ws_url}?token={token}", max_size=None, ssl=ssl) as ws:
        await ws.send(
            proto.encode(
                proto.make_hello(
                    client_name, (K.fx, K.fy, K.cx, K.cy), (K.width, K.height), depth_scale=1000.0
                )
            )
        )
        stats.welcome = proto.decode(await ws.recv())
        if stats.welcome["type"] != "welcome":
            raise proto.ProtocolError(
                "unexpected_message", f"expected welcome, got {stats.welcome}"
            )

        async def receive() -> None:
            async for data in ws:
                msg = proto.decode(data)
                if msg["type"] == "pose":
                    sent_at = in_flight.pop(msg["seq"], None)
                    if sent_at is not None:
                        stats.latencies_ms.append((time.monotonic() - sent_at) * 1e3)
                    # Frames the server dropped in favour of this one are answered by it.
                    for seq in [s for s in in_flight if s < msg["seq"]]:
                        in_flight.pop(seq)
                    stats.poses.append(msg)
                    if on_pose is not None:
                        on_pose(msg)
                elif msg["type"] == "map_chunk":
                    stats.map_points += msg["count"]
                elif msg["type"] == "error":
                    stats.errors.append(msg)
                    if msg.get("seq") is not None:
                        in_flight.pop(msg["seq"], None)
                elif msg["type"] == "drone_event":
                    stats.drone_events.append(msg)
                if pilot is not None and (command := pilot(msg)) is not None:
                    await ws.send(proto.encode(command))
                answered.set()

        receiver = asyncio.create_task(receive())
        start = time.monotonic()
        try:
            for i in range(n):
                due = start + i / fps
                await asyncio.sleep(max(0.0, due - time.monotonic()))
                while not drop_when_busy and len(in_flight) >= max_in_flight:
                    answered.clear()
                    await asyncio.wait_for(answered.wait(), timeout=30.0)
                if len(in_flight) >= max_in_flight:
                    stats.client_dropped += 1
                    continue
                if not loop_sequence and i >= len(dataset):
                    break
                # Encoding runs off the event loop: the loop may be a server's (the demo).
                message = cache.get(i % len(dataset)) or await asyncio.to_thread(frame_message, i)
                message = {**message, "seq": i}
                in_flight[i] = time.monotonic()
                await ws.send(proto.encode(message))
                stats.sent += 1
            # Wait for the last answers (bounded), then say goodbye.
            await await_answers(in_flight, answered, time.monotonic() + 30.0)
            await ws.send(proto.encode(proto.make_bye("done")))
            await asyncio.wait_for(receiver, timeout=10.0)
        except (asyncio.TimeoutError, websockets.ConnectionClosed):
            pass
        finally:
            receiver.cancel()
    return stats


def latency_summary(stats: ReplayStats) -> dict:
    lat = np.array(stats.latencies_ms) if stats.latencies_ms else np.array([np.nan])
    return {
        "sent": stats.sent,
        "poses": len(stats.poses),
        "client_dropped": stats.client_dropped,
        "server_dropped": stats.poses[-1]["dropped"] if stats.poses else 0,
        "errors": len(stats.errors),
        "p50_ms": float(np.percentile(lat, 50)),
        "p95_ms": float(np.percentile(lat, 95)),
        "p99_ms": float(np.percentile(lat, 99)),
    }
