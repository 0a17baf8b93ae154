"""The REST API's answers from a real server validate against the OpenAPI document's models, field
for field (the document itself: tests/unit/transport/test_openapi.py)."""

from __future__ import annotations

import asyncio
import time

import httpx
import pydantic
import pytest

from server.datasets import open_dataset
from server.transport.schemas import CourseBest, ErrorBody, SessionCreated, SessionStatus
from tests.conftest import Stream, auth


def strictly(model: type[pydantic.BaseModel], body: dict) -> pydantic.BaseModel:
    """``body`` validated by ``model``, and every field it holds (nested too) declared there:
    the document must name all of them."""
    parsed = model.model_validate(body)

    def undeclared(m: pydantic.BaseModel, where: str) -> list[str]:
        out = [f"{where}{k}" for k in (m.model_extra or {})]
        for name in type(m).model_fields:
            value = getattr(m, name)
            if isinstance(value, pydantic.BaseModel):
                out += undeclared(value, f"{where}{name}.")
        return out

    assert not undeclared(parsed, ""), f"{model.__name__} lacks {undeclared(parsed, '')}"
    return parsed


def test_a_real_servers_answers_validate_against_their_models(live_server, shared_data):
    server = live_server(session_ttl_s=1.0)
    http = httpx.Client(timeout=60)  # a loaded machine answers a status slowly
    ds = open_dataset(shared_data / "synthetic_room0")
    r = http.post(f"{server.url}/api/sessions")
    assert r.status_code == 201
    created = strictly(SessionCreated, r.json())
    assert created.websocket == f"{server.ws_url}/ws/sessions/{created.id}"
    url, headers = f"{server.url}/api/sessions/{created.id}", auth(created.token)

    before = strictly(SessionStatus, http.get(url, headers=headers).json())
    assert before.intrinsics is None and before.drone is None and not before.closed
    assert before.worker is not None and before.worker.kind == "process"

    async def session() -> None:
        stream = await Stream(server.ws_url, created.id, created.token, ds).open()
        await stream.send_range(range(15))
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:  # the drone spawns with the first flight map
            if http.get(url, headers=headers).json()["drone"]["spawned"]:
                break
            await asyncio.sleep(0.2)
        await stream.close()

    asyncio.run(session())
    live = strictly(SessionStatus, http.get(url, headers=headers).json())
    assert live.frames_processed == 15 and live.intrinsics.width == 640
    assert live.drone.spawned and len(live.drone.position) == 3 and live.drone.events["spawned"]

    deadline = time.monotonic() + 30  # no connection for session_ttl_s: closed and saved
    while not (body := http.get(url, headers=headers).json())["closed"]:
        assert time.monotonic() < deadline, "the idle session was never closed"
        time.sleep(0.2)
    closed = strictly(SessionStatus, body)
    assert closed.frames_processed == 15 and closed.tracking_lost is False

    for kind, wrong in (("unauthorized", {}), ("not_found", auth("x" * 43))):
        r = http.get(url, headers=wrong)
        assert r.status_code == {"unauthorized": 401, "not_found": 404}[kind]
        assert strictly(ErrorBody, r.json()).error.code == kind
    r = http.get(f"{url}/map.ply", headers=headers)
    assert r.headers["content-type"] == "application/octet-stream"
    assert r.content.startswith(b"ply\nformat binary_little_endian 1.0\n")
    r = http.get(f"{url}/trajectory.tum", headers=headers)
    assert r.headers["content-type"].startswith("text/plain")
    lines = [line for line in r.text.splitlines() if not line.startswith("#")]
    assert len(lines) == closed.trajectory_poses == 15
    assert float(lines[0].split()[0]) == pytest.approx(ds[0].timestamp, abs=1e-6)
    r = http.get(f"{url}/course/best", headers=headers)  # no course flown: an empty list
    assert strictly(CourseBest, r.json()).results == []
