"""The REST API's OpenAPI document: every answer has a schema with its fields described (the bodies
a real server sends validate against those models, field for field:
tests/server/test_openapi_server.py)."""

from __future__ import annotations

import json

import pytest

from server.config import Config, ServerConfig
from server.transport.app import create_app

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


def test_validation_answers_are_documented_as_the_error_body_the_server_sends(openapi):
    """FastAPI would document 422 as its own ``{"detail": [...]}``; the server answers
    ``{"error": {code, message}}`` (app.py's handler), and the schema says so."""
    assert "HTTPValidationError" not in json.dumps(openapi)
    answer_422 = answer(openapi, "/api/sessions", "post", 422)
    assert answer_422["content"]["application/json"]["schema"]["$ref"].endswith("/ErrorBody")
