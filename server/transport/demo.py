"""The bundled demo session: the server replays its synthetic sequence to itself over a real
WebSocket, so a newcomer sees poses and a growing map without a phone."""

from __future__ import annotations

import asyncio
import logging

from fastapi import FastAPI

from server.client.replay import replay
from server.client.tour import TourPilot
from server.datasets import open_dataset
from server.datasets.demo import demo_sequence_path

log = logging.getLogger(__name__)


async def run_demo(app: FastAPI) -> None:
    settings, manager = app.state.settings, app.state.manager
    path = await asyncio.to_thread(demo_sequence_path)
    dataset = open_dataset(path, "tum")
    session, token = manager.create()
    app.state.demo = {"id": session.id, "token": token}
    scheme = "https" if settings.tls else "http"
    base = f"{scheme}://{settings.host}:{settings.port}"
    log.warning(
        "demo session %s (token %s): map at %s/api/sessions/%s/map.ply "
        "(header 'Authorization: Bearer <token>')",
        session.id,
        token,
        base,
        session.id,
    )
    await asyncio.sleep(0.5)  # let uvicorn start listening
    ws_url = f"{'wss' if settings.tls else 'ws'}://{settings.host}:{settings.port}/ws/sessions/{session.id}"
    ssl = None
    if settings.tls:
        import ssl as ssl_module

        ssl = ssl_module.create_default_context()
        ssl.check_hostname, ssl.verify_mode = False, ssl_module.CERT_NONE
    try:
        stats = await replay(
            ws_url,
            token,
            dataset,
            fps=settings.demo_fps,
            client_name="demo",
            ssl=ssl,
            pilot=TourPilot(),
        )
        arrivals = sum(e["event"] == "arrived" for e in stats.drone_events)
        log.warning(
            "demo session %s: %d frames sent, %d poses, %d map points streamed, "
            "the drone reached %d targets",
            session.id,
            stats.sent,
            len(stats.poses),
            stats.map_points,
            arrivals,
        )
    except Exception:
        log.exception("demo replay failed")
