"""A client written from the published spec alone runs a whole session against a real server.

The client below imports nothing from ``server``: it reads the message shapes, error codes,
close codes and limits from the ``protocol.json`` the running server serves, and everything
else from PROTOCOL.md's text (the REST answers, the frame encodings, the drone's rules). If it
needs something the spec does not say, the spec is incomplete. (The server is started in this
process by the shared fixture, as in the other server tests.)
"""

from __future__ import annotations

import asyncio
import json
import re
import time
import zlib
from pathlib import Path

import cv2
import httpx
import msgpack
import numpy as np
import pytest
import websockets

FRAMES = 24
PY_TYPES = {
    "int": int,
    "float": (int, float),
    "str": str,
    "bytes": bytes,
    "bool": bool,
    "list": list,
    "map": dict,
}


# ---- the client: spec, messages, a socket ---------------------------------------------------


class Spec:
    """protocol.json as served: messages by name, errors by name, close codes by name."""

    def __init__(self, doc: dict) -> None:
        self.version = doc["version"]
        self.messages = doc["messages"]
        self.errors = {e["name"]: e for e in doc["errors"]}
        self.closes = {c["name"]: c["code"] for c in doc["close_codes"]}
        self.limits = doc["limits"]

    def check(self, message: dict) -> dict:
        """A server message as the spec defines it: a known type, every required field, each
        field of its type and within its enum."""
        spec = self.messages[message["type"]]
        assert spec["direction"] == "server_to_client", message["type"]
        for field in spec["fields"]:
            name = field["name"]
            if name not in message:
                assert not field["required"], (message["type"], name)
                continue
            value = message[name]
            assert isinstance(value, PY_TYPES[field["type"]]), (message["type"], name, value)
            if "enum" in field:
                assert value in field["enum"], (message["type"], name, value)
            if "length" in field:
                assert len(value) == field["length"], (message["type"], name)
        return message

    def make(self, kind: str, **fields) -> dict:
        """A client message; refuses fields the spec does not list, and checks the required."""
        spec = self.messages[kind]
        assert spec["direction"] == "client_to_server"
        names = {f["name"] for f in spec["fields"]}
        assert set(fields) <= names, set(fields) - names
        required = {f["name"] for f in spec["fields"] if f["required"]}
        assert required <= set(fields), required - set(fields)
        return {"type": kind, **fields}


class TumSequence:
    """A TUM RGB-D folder read as files: JPEG bytes as they are, depth PNGs (uint16)."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.camera = json.loads((folder / "intrinsics.json").read_text())

        def listing(name: str) -> list[tuple[float, str]]:
            rows = (line.split() for line in (folder / name).read_text().splitlines())
            return [(float(r[0]), r[1]) for r in rows if r and not r[0].startswith("#")]

        self.colour, self.depth = listing("rgb.txt"), listing("depth.txt")

    def frame(self, i: int) -> tuple[float, bytes, np.ndarray]:
        stamp, colour = self.colour[i]
        depth = cv2.imread(str(self.folder / self.depth[i][1]), cv2.IMREAD_UNCHANGED)
        return stamp, (self.folder / colour).read_bytes(), depth


def zlib_depth(depth_u16: np.ndarray) -> bytes:
    """PROTOCOL.md: one zlib stream of width*height little-endian uint16, row-major."""
    return zlib.compress(depth_u16.astype("<u2").tobytes())


class Socket:
    """One WebSocket: sends msgpack maps, hands back the answers; keeps the unasked ones."""

    UNASKED = {"map_chunk", "drone_state", "drone_event"}

    def __init__(self, spec: Spec, ws) -> None:
        self.spec, self.ws = spec, ws
        self.unasked: list[dict] = []

    @classmethod
    async def open(cls, spec: Spec, url: str) -> Socket:
        return cls(spec, await websockets.connect(url, max_size=None))

    async def send(self, message: dict | bytes) -> None:
        data = message if isinstance(message, bytes) else msgpack.packb(message, use_bin_type=True)
        await self.ws.send(data)

    async def receive(self, timeout_s: float = 60) -> dict:
        data = await asyncio.wait_for(self.ws.recv(), timeout_s)
        assert isinstance(data, bytes), "the server sends binary frames only"
        message = self.spec.check(msgpack.unpackb(data, raw=False))
        if message["type"] in self.UNASKED:
            self.unasked.append(message)
        return message

    async def answer(self, timeout_s: float = 60) -> dict:
        """The next message that is not one the server sends unasked."""
        while (message := await self.receive(timeout_s))["type"] in self.UNASKED:
            pass
        return message

    async def wait_for(self, found, timeout_s: float = 60, since: int = 0) -> dict:
        """The first unasked message from index ``since`` on (those received while waiting for
        answers included), or the first message to come, for which ``found(message)``."""
        for message in self.unasked[since:]:
            if found(message):
                return message
        deadline = time.monotonic() + timeout_s
        while True:
            message = await self.receive(max(0.1, deadline - time.monotonic()))
            if found(message):
                return message

    async def expect_error(self, name: str, **echo) -> dict:
        """The error ``name`` as the spec defines it; a fatal one is followed by its close."""
        error = await self.answer()
        spec = self.spec.errors[name]
        assert error["type"] == "error" and error["name"] == name, error
        assert error["code"] == spec["code"] and error["fatal"] == spec["fatal"], error
        for key, value in echo.items():
            assert error.get(key) == value, (key, error)
        if spec["fatal"]:
            with pytest.raises(websockets.ConnectionClosed):
                while True:
                    await self.receive(10)
            assert self.ws.close_code == spec["close"], (name, self.ws.close_code)
        return error


# ---- the session -----------------------------------------------------------------------------


def test_a_client_built_from_the_spec_alone_runs_a_session(live_server, shared_data):
    server = live_server()
    http = httpx.Client(base_url=server.url, timeout=60)
    spec = Spec(http.get("/protocol.json").json())  # PROTOCOL.md: served unchanged, no token

    r = http.post("/api/sessions")
    assert r.status_code == 201
    created = r.json()
    sid, token = created["id"], created["token"]
    assert re.fullmatch("[0-9a-f]{16}", sid) and token not in created["websocket"]
    ws_url = f"{created['websocket']}?token={token}"
    headers = {"Authorization": f"Bearer {token}"}
    sequence = TumSequence(shared_data / "synthetic_room0")
    cam = sequence.camera

    def hello(**changes) -> dict:
        fields = {
            "version": spec.version,
            "client_name": "spec-client/1",
            "intrinsics": [cam["fx"], cam["fy"], cam["cx"], cam["cy"]],
            "colour_size": [cam["width"], cam["height"]],
            "depth_size": [cam["width"], cam["height"]],
            "depth_scale": cam["depth_scale"],
        }
        return spec.make("hello", **{**fields, **changes})

    def frame(seq: int, index: int, **changes) -> dict:
        stamp, colour, depth = sequence.frame(index)
        fields = {"seq": seq, "timestamp": stamp, "colour": colour}
        if index % 2:  # both depth encodings of the spec
            fields |= {"depth": zlib_depth(depth), "depth_format": "zlib"}
        else:
            fields |= {"depth": cv2.imencode(".png", depth)[1].tobytes(), "depth_format": "png"}
        return spec.make("frame", **{**fields, **changes})

    async def session() -> dict:
        main = await Socket.open(spec, ws_url)
        await main.send(hello())
        welcome = await main.answer()
        assert welcome["type"] == "welcome" and welcome["session_id"] == sid

        # Frames one at a time, each answered by its pose (its timestamp echoed).
        poses = []
        for seq in range(FRAMES):
            await main.send(frame(seq, seq))
            pose = await main.answer()
            assert pose["type"] == "pose" and pose["seq"] == seq, pose
            assert pose["timestamp"] == sequence.frame(seq)[0]
            assert {"decode", "track", "server_total"} <= set(pose["timings_ms"])
            poses.append(pose)
        assert {p["state"] for p in poses} <= {"ok", "weak"}
        T = np.array(poses[-1]["T_world_camera"]).reshape(4, 4)  # row-major
        np.testing.assert_allclose(T[3], [0, 0, 0, 1])
        assert 0.05 < np.linalg.norm(T[:3, 3]) < 5  # the camera moved, metres

        # The drone: 'spawned' before any drone_state, then states at the simulation rate.
        spawned = await main.wait_for(
            lambda m: m["type"] == "drone_event" and m["event"] == "spawned"
        )
        kinds = [m["type"] for m in main.unasked]
        first_state = kinds.index("drone_state") if "drone_state" in kinds else len(kinds)
        assert first_state > main.unasked.index(spawned)
        await main.wait_for(lambda m: m["type"] == "drone_state")

        # The map preview: count points of 12 bytes (float32 x, y, z) and 3 of colour.
        chunks = [m for m in main.unasked if m["type"] == "map_chunk"]
        assert chunks and chunks[0]["chunk"] == 0
        for chunk in chunks:
            points = np.frombuffer(chunk["points"], "<f4").reshape(-1, 3)
            assert len(points) == chunk["count"] == len(chunk["colours"]) // 3
            assert np.isfinite(points).all()

        # goto a reachable point: where the drone spawned (world frame). Arrives and hovers.
        target = [float(v) for v in spawned["position"]]
        since = len(main.unasked)
        await main.send(spec.make("command", id=7, name="goto", target=target))
        arrived = await main.wait_for(
            lambda m: (
                (m["type"] == "drone_event" and m["event"] == "arrived") or m["type"] == "error"
            ),
            timeout_s=25,  # under idle_timeout_s: the client sends nothing meanwhile
            since=since,
        )
        assert arrived["type"] == "drone_event" and arrived.get("command_id") == 7, arrived
        assert np.linalg.norm(np.subtract(arrived["position"], target)) <= 0.1 + 1e-6
        assert "({:.2f}, {:.2f}, {:.2f}) m".format(*target) in arrived["message"]  # world frame

        # Each non-fatal error class, answered with its seq or command id; the session goes on.
        seq = FRAMES
        await main.send(frame(seq, 0, colour=b"\x00" * 64))
        await main.expect_error("corrupt_image", seq=seq)
        seq += 1
        await main.send(
            frame(seq, 1, depth=zlib_depth(np.ones((10, 10), np.uint16)), depth_format="zlib")
        )
        await main.expect_error("size_mismatch", seq=seq)
        seq += 1
        zeros = np.zeros((cam["height"], cam["width"]), np.uint16)
        await main.send(frame(seq, 1, depth=zlib_depth(zeros), depth_format="zlib"))
        await main.expect_error("bad_depth", seq=seq)
        await main.send(frame(seq, 1))  # the same seq again
        await main.expect_error("bad_sequence", seq=seq)
        await main.send(spec.make("command", id=8, name="takeoff"))  # it is flying already
        await main.expect_error("bad_command", command_id=8)
        await main.send(spec.make("command", id=9, name="goto", target=[100.0, 100.0, 100.0]))
        await main.expect_error("unreachable_target", command_id=9)
        await main.send(frame(seq + 1, FRAMES))
        assert (await main.answer())["type"] == "pose"

        # bye: the frames in flight are answered, then close 1000.
        await main.send(spec.make("bye", reason="done"))
        with pytest.raises(websockets.ConnectionClosed):
            while True:
                await main.receive(10)
        assert main.ws.close_code == 1000
        return {"poses": poses, "after_errors": seq + 1}

    result = asyncio.run(session())

    # PROTOCOL.md: a bye ends the connection, not the session.
    status = http.get(f"/api/sessions/{sid}", headers=headers).json()
    assert status["closed"] is False and status["frames_processed"] == FRAMES + 1
    assert status["intrinsics"]["fx"] == cam["fx"] and status["drone"]["spawned"]

    # Downloads: the TUM trajectory echoes the frames' timestamps; map.ply as documented.
    text = http.get(f"/api/sessions/{sid}/trajectory.tum", headers=headers).text
    rows = [line.split() for line in text.splitlines() if not line.startswith("#")]
    assert len(rows) == FRAMES + 1 and all(len(r) == 8 for r in rows)
    assert [float(r[0]) for r in rows[:FRAMES]] == pytest.approx(
        [p["timestamp"] for p in result["poses"]], abs=1e-6
    )
    last = np.array(result["poses"][FRAMES - 1]["T_world_camera"]).reshape(4, 4)
    np.testing.assert_allclose([float(v) for v in rows[FRAMES - 1][1:4]], last[:3, 3], atol=1e-6)
    # The map fuses behind the poses (at a lower priority): until a surface exists, map.ply is
    # 409 map_unavailable, which a client retries.
    deadline = time.monotonic() + 60
    while (reply := http.get(f"/api/sessions/{sid}/map.ply", headers=headers)).status_code != 200:
        assert reply.status_code == 409, reply.text
        assert reply.json()["error"]["code"] == "map_unavailable"
        assert time.monotonic() < deadline, "no surface in the map after 60 s"
        time.sleep(0.5)
    ply = reply.content
    header, _, body = ply.partition(b"end_header\n")
    lines = header.decode().splitlines()
    assert "format binary_little_endian 1.0" in lines
    count = int(next(line for line in lines if line.startswith("element vertex")).split()[2])
    props = [line.split()[1:] for line in lines if line.startswith("property")]
    assert props == [
        ["double", "x"],
        ["double", "y"],
        ["double", "z"],
        ["uchar", "red"],
        ["uchar", "green"],
        ["uchar", "blue"],
    ]
    vertices = np.frombuffer(body, np.dtype([("xyz", "<f8", 3), ("rgb", "u1", 3)]), count)
    assert count > 1000 and len(body) == count * 27 and np.isfinite(vertices["xyz"]).all()

    # Each fatal error class on a socket of its own: the error, then its close code.
    async def fatal(name: str, *messages, hello_first: bool = False, url: str = ws_url) -> None:
        socket = await Socket.open(spec, url)
        if hello_first:
            await socket.send(hello())
            assert (await socket.answer())["type"] == "welcome"
        for message in messages:
            await socket.send(message)
        await socket.expect_error(name)

    async def fatal_errors() -> None:
        await fatal("malformed_message", b"\xc1")
        await fatal("malformed_message", msgpack.packb([1, 2]))
        await fatal("unknown_type", msgpack.packb({"type": "teleport"}))
        without_name = {k: v for k, v in hello().items() if k != "client_name"}
        await fatal("missing_field", msgpack.packb(without_name))
        await fatal("invalid_field", msgpack.packb(hello(intrinsics=[500.0, 500.0, 320.0])))
        await fatal("message_too_big", b"\x00" * (spec.limits["max_message_bytes"] + 1))
        await fatal("unexpected_message", msgpack.packb(frame(0, 0), use_bin_type=True))
        await fatal("unexpected_message", msgpack.packb(hello()), hello_first=True)
        await fatal("version_mismatch", msgpack.packb(hello(version=spec.version + 1)))
        await fatal("bad_intrinsics", msgpack.packb(hello(intrinsics=[5.0, 5.0, 320.0, 240.0])))
        await fatal("bad_image_size", msgpack.packb(hello(colour_size=[8, 6], depth_size=[8, 6])))
        # A wrong token: the error and close 4003 come without waiting for a hello.
        await fatal("unauthorized", url=f"{created['websocket']}?token={'x' * len(token)}")
        # The newest socket wins: the older one hears session_taken_over, close 4009.
        older = await Socket.open(spec, ws_url)
        await older.send(hello())
        assert (await older.answer())["type"] == "welcome"
        newer = await Socket.open(spec, ws_url)
        await older.expect_error("session_taken_over")
        await newer.ws.close()

    asyncio.run(fatal_errors())
    assert http.get(f"/api/sessions/{sid}", headers=headers).json()["frames_processed"] == (
        FRAMES + 1
    )
    assert result["after_errors"] == FRAMES + 3


def test_a_command_without_its_field_is_refused_with_its_id(live_server, shared_data):
    server = live_server()
    http = httpx.Client(base_url=server.url, timeout=60)
    spec = Spec(http.get("/protocol.json").json())
    created = http.post("/api/sessions").json()
    cam = TumSequence(shared_data / "synthetic_room0").camera

    async def run() -> None:
        socket = await Socket.open(spec, f"{created['websocket']}?token={created['token']}")
        hello = spec.make(
            "hello",
            version=spec.version,
            client_name="spec-client/1",
            intrinsics=[cam["fx"], cam["fy"], cam["cx"], cam["cy"]],
            colour_size=[cam["width"], cam["height"]],
            depth_size=[cam["width"], cam["height"]],
            depth_scale=cam["depth_scale"],
        )
        await socket.send(hello)
        assert (await socket.answer())["type"] == "welcome"
        await socket.send(spec.make("command", id=8, name="goto"))  # no target
        await socket.expect_error("bad_command", command_id=8)

    asyncio.run(run())
