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
    # The token stays out of the log: the operator finds the session's files on disk.
    log.warning(
        "demo session %s: its map and trajectory are saved under %s",
        session.id,
        settings.data_dir / "sessions" / session.id,
    )
    await asyncio.sleep(0.5)  # let uvicorn start listening
    scheme = "wss" if settings.tls else "ws"
    ws_url = f"{scheme}://{settings.host}:{settings.port}/ws/sessions/{session.id}"
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
    except Exception:
        log.exception("demo session %s: the replay could not start", session.id)
        return
    arrivals = sum(e["event"] == "arrived" for e in stats.drone_events)
    summary = (
        f"{stats.describe()}; {len(stats.poses)} poses, {stats.map_points} map points streamed, "
        f"the drone reached {arrivals} targets"
    )
    if stats.completed:
        log.warning("demo session %s: %s", session.id, summary)
    else:
        log.error("demo session %s ended early: %s", session.id, summary)
