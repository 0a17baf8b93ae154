"""The REST API's OpenAPI document: every answer has a schema with its fields described, and the
bodies a real server sends validate against those models, field for field."""

from __future__ import annotations

import asyncio
import json
import time

import httpx
import pydantic
import pytest
from conftest import Stream, auth

from server.config import Config, ServerConfig
from server.datasets import open_dataset
from server.transport.app import create_app
from server.transport.schemas import CourseBest, ErrorBody, SessionCreated, SessionStatus

SESSION = "/api/sessions/{session_id}"


@pytest.fixture(scope="module")
def openapi(tmp_path_factory) -> dict:
    return create_app(
        Config(server=ServerConfig(data_dir=tmp_path_factory.mktemp("data")))
    ).openapi()


def schema(openapi: dict, ref: dict) -> dict:
    return openapi["components"]["schemas"][ref["$ref"].rsplit("/", 1)[1]]


def answer(openapi: dict, path: str, method: str, code: int) -> dict:
    return openapi["paths"][path][method]["responses"][str(code)]


def json_model(openapi: dict, path: str, method: str, code: int) -> dict:
    return schema(
        openapi, answer(openapi, path, method, code)["content"]["application/json"]["schema"]
    )


def described(props: dict) -> bool:
    return all(p.get("description") for p in props.values())


def test_session_creation_documents_201_and_its_body(openapi):
    assert set(openapi["paths"]["/api/sessions"]["post"]["responses"]) >= {"201", "429", "503"}
    created = json_model(openapi, "/api/sessions", "post", 201)
    assert set(created["required"]) == {"id", "token", "websocket"} and described(
        created["properties"]
    )
    assert "?token=" in created["properties"]["websocket"]["description"]  # not in the URL
    error = json_model(openapi, "/api/sessions", "post", 429)
    assert schema(openapi, error["properties"]["error"])["required"] == ["code", "message"]


def test_status_documents_every_field_with_its_meaning(openapi):
    status = json_model(openapi, SESSION, "get", 200)
    props = status["properties"]
    for name in (
        "id",
        "created_at",
        "closed",
        "frames_received",
        "frames_processed",
        "frames_dropped",
        "frames_failed",
        "tracking_states",
        "trajectory_poses",
        "map",
        "intrinsics",
        "drone",
        "snapshot_error",
        "tracking_lost",
        "worker",
    ):
        assert name in props, name
    assert described(props)
    assert "session_ttl_s" in props["closed"]["description"]  # a bye does not close it
    drone = schema(openapi, props["drone"]["anyOf"][0])
    assert "world frame" in drone["properties"]["position"]["description"]
    assert described(schema(openapi, props["map"])["properties"])
    for code in (401, 404):
        assert "error" in json_model(openapi, SESSION, "get", code)["properties"]


def test_downloads_document_their_media_types(openapi):
    for name, media in (
        ("map.ply", "application/octet-stream"),
        ("mesh.ply", "application/octet-stream"),
        ("mesh.glb", "model/gltf-binary"),
        ("trajectory.tum", "text/plain"),
    ):
        ok = answer(openapi, f"{SESSION}/{name}", "get", 200)
        assert list(ok["content"]) == [media], name
        assert ok["content"][media]["schema"]["format"] == "binary"
    doc = openapi["paths"][f"{SESSION}/trajectory.tum"]["get"]["description"]
    assert "timestamp echoed" in doc and "T_world_camera" in doc
    assert "double x, y, z" in openapi["paths"][f"{SESSION}/map.ply"]["get"]["description"]
    mesh = openapi["paths"][f"{SESSION}/mesh.ply"]["get"]
    assert [p["name"] for p in mesh["parameters"] if p["in"] == "query"] == ["frame"]
    assert "y up" in openapi["paths"][f"{SESSION}/mesh.glb"]["get"]["description"]
    flight = answer(openapi, f"{SESSION}/flights/{{flight_id}}.tum", "get", 200)
    assert list(flight["content"]) == ["text/plain"]
    assert "204" in openapi["paths"][SESSION]["delete"]["responses"]


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


def test_validation_answers_are_documented_as_the_error_body_the_server_sends(openapi):
    """FastAPI would document 422 as its own ``{"detail": [...]}``; the server answers
    ``{"error": {code, message}}`` (app.py's handler), and the schema says so."""
    assert "HTTPValidationError" not in json.dumps(openapi)
    answer_422 = answer(openapi, "/api/sessions", "post", 422)
    assert answer_422["content"]["application/json"]["schema"]["$ref"].endswith("/ErrorBody")
