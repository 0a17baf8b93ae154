"""Bad input against a real server on loopback.

Every case gets an error message with a documented code; the offending socket either goes on or
is closed with the error's documented close code; the server keeps serving; and a healthy
session streaming real frames alongside (a background thread) keeps receiving poses throughout.
Hand-written cases first, then random variants from hypothesis: mutations of valid messages fed
to the codec in-process (many), and through the live socket (a bounded number).
"""

from __future__ import annotations

import asyncio
import contextlib
import threading
import time
import zlib

import cv2
import httpx
import msgpack
import numpy as np
import pytest
import websockets
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from server import protocol as P
from server.client.connection import Connection, Socket
from server.datasets import open_dataset
from tests.conftest import LiveServer, auth
from tests.support.rest import drone_spawned, wait_for_status

MAX_BYTES = 2 * 2**20  # the module server's max_message_bytes
SIZE = (64, 48)  # (width, height) of the hand-made frames: cheap to decode and track
HELLO = P.make_hello("bad-input", (60.0, 60.0, 31.5, 23.5), SIZE)
UNASKED = {"map_chunk", "drone_state", "drone_event"}  # may arrive between answers
MAX_HEALTHY_GAP_S = 3.0  # longest silence allowed on the healthy session (2 shared cores)


def _image() -> np.ndarray:
    rng = np.random.default_rng(0)
    return cv2.GaussianBlur(rng.integers(0, 256, (SIZE[1], SIZE[0], 3), dtype=np.uint8), (5, 5), 0)


IMAGE = _image()
DEPTH = np.full((SIZE[1], SIZE[0]), 1.5, np.float32)  # metres


def frame(number: int, **changes) -> dict:
    """A valid frame of SIZE (PNG depth) with seq ``number``, fields replaced by ``changes``."""
    return {**P.make_frame(number, 0.1 * number, IMAGE, DEPTH), **changes}


def raw(message) -> bytes:
    """msgpack without the codec's checks (which would refuse to encode bad messages)."""
    return msgpack.packb(message, use_bin_type=True)


def without(message: dict, key: str) -> dict:
    return {k: v for k, v in message.items() if k != key}


def assert_documented(error: dict, name: str, seq: int | None = None) -> None:
    """An error message as protocol.json defines ``name``: code, fatality, a readable message."""
    assert error["type"] == "error", error
    assert error["name"] == name, error
    assert error["code"] == P.ERRORS[name]["code"] and error["fatal"] == P.ERRORS[name]["fatal"]
    assert isinstance(error["message"], str) and len(error["message"]) > 5
    if seq is not None:
        assert error.get("seq") == seq, error


# ---- a bare client and a healthy neighbour --------------------------------------------------


class Client(Socket):
    """The protocol client's lower layer, unchecked: sends anything, reads answers, sees how the
    socket ends. ``session``: (id, token) of the session it is on, when ``fresh_session`` made
    it."""

    session: tuple[str, str] | None = None

    async def send(self, message: dict | bytes | str) -> None:
        await self.send_raw(raw(message) if isinstance(message, dict) else message)

    async def answer(self, timeout: float = 15.0) -> dict:
        """The next welcome, pose or error (skipping map chunks and drone messages)."""
        while True:
            msg = await self.next(timeout)
            if msg["type"] not in UNASKED:
                return msg

    async def next(self, timeout: float = 15.0) -> dict:
        """The next message of any type."""
        return await self.receive(timeout)

    async def close_code(self, timeout: float = 15.0) -> int:
        """Wait for the server to close; fails on any answer before the close."""
        try:
            msg = await self.answer(timeout)
        except websockets.ConnectionClosed as closed:
            return closed.rcvd.code if closed.rcvd else 1006
        raise AssertionError(f"expected a close, got {msg}")

    async def hello(self, message: dict = HELLO) -> dict:
        await self.send(message)
        welcome = await self.answer()
        assert welcome["type"] == "welcome", welcome
        return welcome


@contextlib.asynccontextmanager
async def fresh_session(server: LiveServer):
    """A Client on a new session's socket; the session is deleted afterwards (each live session
    holds its TSDF buffers, tens of MB)."""
    sid, token = server.create_session()
    try:
        async with await Client.connect(f"{server.ws_url}/ws/sessions/{sid}", token) as client:
            client.session = (sid, token)
            yield client
    finally:
        httpx.delete(f"{server.url}/api/sessions/{sid}", headers=auth(token))


def run(coro):
    return asyncio.run(coro)


class HealthyStream:
    """A session streaming real frames (forward, backward, ...) in a background thread, at up to
    ``fps`` with at most two frames in flight; it records when each pose arrived."""

    def __init__(self, server: LiveServer, dataset, fps: float = 5.0, frames: int = 20) -> None:
        self.server, self.fps = server, fps
        self.K = dataset.intrinsics
        self.frames = [
            P.encode(P.make_frame(i, dataset[i].timestamp, dataset[i].colour, dataset[i].depth))
            for i in range(frames)
        ]
        self.pose_times: list[float] = []
        self.errors: list[dict] = []
        self.close_code: int | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=lambda: asyncio.run(self._run()), daemon=True)

    def hello(self, name: str) -> dict:
        K = self.K
        return P.make_hello(name, (K.fx, K.fy, K.cx, K.cy), (K.width, K.height))

    def frame(self, index: int, seq: int) -> dict:
        """Frame ``index`` of the sequence, numbered ``seq`` and timed at 0.1 s per seq."""
        return {**msgpack.unpackb(self.frames[index]), "seq": seq, "timestamp": 0.1 * seq}

    def start(self) -> HealthyStream:
        self._thread.start()
        self.wait_for_pose_after(time.monotonic(), timeout=30)
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=30)

    def wait_for_pose_after(self, t: float, timeout: float = 10.0) -> float:
        """Seconds from ``t`` until the next pose arrived; fails after ``timeout``."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            later = [p for p in self.pose_times if p > t]
            if later:
                return later[0] - t
            time.sleep(0.02)
        raise AssertionError(
            f"healthy session: no pose for {timeout} s "
            f"(errors {self.errors}, close {self.close_code})"
        )

    def longest_gap(self) -> float:
        return float(np.diff(self.pose_times).max()) if len(self.pose_times) > 1 else 0.0

    async def _run(self) -> None:
        sid, token = self.server.create_session()
        order = [*range(len(self.frames)), *range(len(self.frames) - 2, 0, -1)]  # ping-pong
        url = f"{self.server.ws_url}/ws/sessions/{sid}"
        async with await Connection.open(url, token, self.hello("healthy")) as conn:

            def on_message(msg: dict, latency_ms: float | None) -> None:
                if msg["type"] == "pose":
                    self.pose_times.append(time.monotonic())
                elif msg["type"] == "error":
                    self.errors.append(msg)

            conn.start(on_message)
            seq = 0
            while not self._stop.is_set() and conn.receiving:
                if len(conn.in_flight) < P.LIMITS["max_in_flight"]:
                    await conn.send_frame(self.frame(order[seq % len(order)], seq))
                    seq += 1
                await asyncio.sleep(1 / self.fps)
            try:
                await conn.bye("done", 15)
            finally:
                self.close_code = conn.close_code or 1006


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    server = LiveServer(
        tmp_path_factory.mktemp("bad_input") / "data",
        max_message_bytes=MAX_BYTES,
        max_sessions=1000,
        create_rate_per_min=0,
        snapshot_interval_s=3600,
    )
    yield server
    server.stop()


@pytest.fixture(scope="module")
def healthy(server, shared_data):
    stream = HealthyStream(server, open_dataset(shared_data / "synthetic_room0")).start()
    yield stream
    stream.stop()


@pytest.fixture
def neighbour_keeps_going(server, healthy):
    """After the test: the server answers health checks and the healthy session gets a pose."""
    yield
    end = time.monotonic()
    assert httpx.get(f"{server.url}/healthz").json()["status"] == "ok"
    healthy.wait_for_pose_after(end)
    assert not healthy.errors and healthy.close_code is None


# ---- fatal cases: error, then the documented close --------------------------------------------

NAN, INF = float("nan"), float("inf")
FATAL = {  # id: (hello first?, what is sent, error name)
    "not msgpack": (False, b"\xc1\xc1\xc1", "malformed_message"),
    "truncated msgpack": (False, raw(HELLO)[:-7], "malformed_message"),
    "trailing bytes": (False, raw(HELLO) + b"\x00", "malformed_message"),
    "text frame": (False, "hello", "malformed_message"),
    "empty message": (False, b"", "malformed_message"),
    "a list, not a map": (False, raw([1, 2, 3]), "malformed_message"),
    "no type": (False, raw({"seq": 1}), "malformed_message"),
    "type not str": (False, raw({"type": 5}), "malformed_message"),
    "int map keys": (False, raw({"type": "hello", 1: 2}), "malformed_message"),
    "unknown type": (False, raw({"type": "teleport"}), "unknown_type"),
    "server's message from a client": (False, raw(P.make_welcome("x")), "unknown_type"),
    "hello without intrinsics": (False, raw(without(HELLO, "intrinsics")), "missing_field"),
    "intrinsics a str": (False, raw({**HELLO, "intrinsics": "fx fy cx cy"}), "invalid_field"),
    "three intrinsics": (False, raw({**HELLO, "intrinsics": [60.0, 60.0, 31.5]}), "invalid_field"),
    "sizes as floats": (False, raw({**HELLO, "colour_size": [64.0, 48.0]}), "invalid_field"),
    "NaN intrinsics": (
        False,
        raw({**HELLO, "intrinsics": [NAN, 60.0, 31.5, 23.5]}),
        "invalid_field",
    ),
    "inf depth_scale in hello": (False, raw({**HELLO, "depth_scale": INF}), "invalid_field"),
    "client_name of 10 kB": (False, raw({**HELLO, "client_name": "x" * 10_000}), "invalid_field"),
    "version mismatch": (False, raw({**HELLO, "version": P.VERSION + 1}), "version_mismatch"),
    "version mismatch, other fields": (
        False,
        raw({"type": "hello", "version": 99, "x": 1}),
        "version_mismatch",
    ),
    "focal length of 1e6 px": (
        False,
        raw({**HELLO, "intrinsics": [1e6, 1e6, 31.5, 23.5]}),
        "bad_intrinsics",
    ),
    "negative focal length": (
        False,
        raw({**HELLO, "intrinsics": [-60.0, 60.0, 31.5, 23.5]}),
        "bad_intrinsics",
    ),
    "fx ten times fy": (
        False,
        raw({**HELLO, "intrinsics": [200.0, 20.0, 31.5, 23.5]}),
        "bad_intrinsics",
    ),
    "principal point outside": (
        False,
        raw({**HELLO, "intrinsics": [60.0, 60.0, -5.0, 23.5]}),
        "bad_intrinsics",
    ),
    "zero image size": (False, raw({**HELLO, "colour_size": [0, 0]}), "bad_image_size"),
    "huge image size": (False, raw({**HELLO, "colour_size": [100_000, 75_000]}), "bad_image_size"),
    "depth aspect differs": (False, raw({**HELLO, "depth_size": [64, 64]}), "bad_image_size"),
    "frame before hello": (False, raw(frame(0)), "unexpected_message"),
    "command before hello": (False, raw(P.make_command(1, "hold")), "unexpected_message"),
    "second hello": (True, raw(HELLO), "unexpected_message"),
    "negative seq": (True, raw(frame(0, seq=-1)), "invalid_field"),
    "seq a str": (True, raw(frame(0, seq="1")), "invalid_field"),
    "seq above 2^53": (True, raw(frame(0, seq=2**60)), "invalid_field"),
    "colour a str": (True, raw(frame(0, colour="jpeg")), "invalid_field"),
    "depth_format jpeg": (True, raw(frame(0, depth_format="jpeg")), "invalid_field"),
    "frame depth_scale NaN": (True, raw(frame(0, depth_scale=NAN)), "invalid_field"),
    "frame depth_scale inf": (True, raw(frame(0, depth_scale=INF)), "invalid_field"),
    "frame depth_scale negative": (True, raw(frame(0, depth_scale=-1000.0)), "invalid_field"),
    "frame depth_scale zero": (True, raw(frame(0, depth_scale=0.0)), "invalid_field"),
    "goto with NaN target": (
        True,
        raw({**P.make_command(1, "goto", target=[0, 0, 1]), "target": [NAN, 0.0, 1.0]}),
        "invalid_field",
    ),
    "goto with inf target": (
        True,
        raw({**P.make_command(1, "goto", target=[0, 0, 1]), "target": [0.0, -INF, 1.0]}),
        "invalid_field",
    ),
    "sticks beyond 1": (
        True,
        raw(P.make_command(1, "sticks", sticks=[2, 0, 0, 0])),
        "invalid_field",
    ),
    "oversized garbage": (False, b"\xc1" * (MAX_BYTES + 1), "message_too_big"),
    "oversized frame": (
        True,
        raw(frame(0, colour=b"\xff\xd8\xff" + bytes(MAX_BYTES))),
        "message_too_big",
    ),
}


@pytest.mark.parametrize("case", FATAL, ids=list(FATAL))
def test_a_fatal_case_is_answered_with_its_code_and_closed_with_its_close_code(
    server, neighbour_keeps_going, case
):
    hello_first, payload, name = FATAL[case]

    async def go():
        async with fresh_session(server) as client:
            if hello_first:
                await client.hello()
            await client.send(payload)
            assert_documented(await client.answer(), name)
            return await client.close_code()

    assert run(go()) == P.ERRORS[name]["close"]


# ---- non-fatal cases: error for that frame, the session goes on --------------------------------


def _png8() -> bytes:
    return cv2.imencode(".png", np.full((SIZE[1], SIZE[0]), 9, np.uint8))[1].tobytes()


def _corrupt_idat(png: bytes) -> bytes:
    start = png.index(b"IDAT") + 8
    return png[:start] + bytes(b ^ 0x5A for b in png[start : start + 40]) + png[start + 40 :]


def _zlib_depth(units: np.ndarray) -> bytes:
    return zlib.compress(np.ascontiguousarray(units, "<u2").tobytes())


_ZERO = np.zeros((SIZE[1], SIZE[0]), np.uint16)
NON_FATAL = {  # id: (fields replaced in a valid frame, error name)
    "truncated JPEG": (lambda f: {"colour": f["colour"][: len(f["colour"]) // 2]}, "corrupt_image"),
    "JPEG without start marker": (lambda f: {"colour": b"GIF89a" + f["colour"]}, "corrupt_image"),
    "JPEG without frame header": (
        lambda f: {"colour": b"\xff\xd8\xff\xfe\x00\x02\xff\xd9"},
        "corrupt_image",
    ),
    "colour of another size": (
        lambda f: {"colour": P.encode_jpeg(IMAGE[:24, :32].copy())},
        "size_mismatch",
    ),
    "truncated PNG": (lambda f: {"depth": f["depth"][:-30]}, "corrupt_image"),
    "8-bit PNG": (lambda f: {"depth": _png8()}, "corrupt_image"),
    "PNG with corrupt pixel data": (
        lambda f: {"depth": _corrupt_idat(f["depth"])},
        "corrupt_image",
    ),
    "depth PNG of another size": (
        lambda f: {"depth": P.encode_depth(DEPTH[:24, :32])},
        "size_mismatch",
    ),
    "zlib garbage": (
        lambda f: {"depth_format": "zlib", "depth": b"not a zlib stream"},
        "corrupt_image",
    ),
    "truncated zlib": (
        lambda f: {"depth_format": "zlib", "depth": _zlib_depth(DEPTH * 1000)[:-9]},
        "corrupt_image",
    ),
    "zlib with too few values": (
        lambda f: {"depth_format": "zlib", "depth": _zlib_depth(_ZERO[:10] + 1500)},
        "size_mismatch",
    ),
    "zlib bomb": (
        lambda f: {"depth_format": "zlib", "depth": zlib.compress(bytes(2**26), 9)},
        "size_mismatch",
    ),
    "all-zero depth": (lambda f: {"depth": P.encode_depth(_ZERO)}, "bad_depth"),
    "depth of kilometres (wrong scale)": (lambda f: {"depth_scale": 1.0}, "bad_depth"),
}


@pytest.mark.parametrize("case", NON_FATAL, ids=list(NON_FATAL))
def test_a_bad_frame_is_refused_and_the_session_goes_on(server, neighbour_keeps_going, case):
    change, name = NON_FATAL[case]

    async def go():
        async with fresh_session(server) as client:
            await client.hello()
            await client.send(frame(1))
            assert (await client.answer())["seq"] == 1
            await client.send(frame(2, **change(frame(2))))
            assert_documented(await client.answer(), name, seq=2)
            await client.send(frame(3))
            pose = await client.answer()
            assert pose["type"] == "pose" and pose["seq"] == 3

    run(go())


def test_duplicate_and_out_of_order_frames_are_refused_and_the_session_goes_on(
    server, neighbour_keeps_going
):
    async def go():
        async with fresh_session(server) as client:
            await client.hello()
            await client.send(frame(5))
            assert (await client.answer())["seq"] == 5
            await client.send(frame(5))
            assert_documented(await client.answer(), "bad_sequence", seq=5)
            await client.send(frame(3))
            assert_documented(await client.answer(), "bad_sequence", seq=3)
            await client.send(frame(9))  # gaps are allowed
            pose = await client.answer()
            assert pose["type"] == "pose" and pose["seq"] == 9

    run(go())


@pytest.mark.parametrize(
    "command",
    [
        P.make_command(7, "goto", target=[0.0, 0.0, 1.0]),
        P.make_command(7, "takeoff"),
    ],
    ids=["goto", "takeoff"],
)
def test_a_command_before_the_drone_exists_is_refused_and_the_session_goes_on(
    server, neighbour_keeps_going, command
):
    async def go():
        async with fresh_session(server) as client:
            await client.hello()  # no frame yet, so no map and no drone
            await client.send(command)
            error = await client.answer()
            assert_documented(error, "bad_command")
            assert error["command_id"] == 7 and "spawned" in error["message"], error
            await client.send(frame(1))
            assert (await client.answer())["seq"] == 1

    run(go())


def test_targets_outside_the_map_are_refused_and_the_drone_flies_on(
    server, neighbour_keeps_going, healthy
):
    """With the drone spawned in a real map: far-away and missing targets get their documented
    errors, and frames and commands go on."""

    async def go():
        async with fresh_session(server) as client:
            assert client.session is not None
            await client.hello(healthy.hello("bad-input"))
            spawned = False
            n = len(healthy.frames)
            for seq in range(n):
                await client.send(healthy.frame(seq, seq))
                while (msg := await client.next()).get("seq") != seq:
                    spawned = spawned or (msg.get("event") == "spawned")
                assert msg["type"] == "pose", msg
            # The drone spawns with the first map that reaches its flight thread, behind the
            # mapper (which lags far behind the poses on a loaded machine): until the status says
            # it has (or that every fused frame reached the drone's map, and none spawned it)...
            await asyncio.to_thread(
                wait_for_status, server.url, *client.session, drone_spawned, "the drone to spawn"
            )
            while not spawned:  # ...and its drone_event is here
                spawned = (await client.next()).get("event") == "spawned"
            for command_id, target in enumerate([[1e4, -1e4, 1e4], [40.0, 0.0, 0.0]], start=1):
                await client.send(P.make_command(command_id, "goto", target=target))
                error = await client.answer()
                assert_documented(error, "unreachable_target")
                assert error["command_id"] == command_id, error
                assert "outside the mapped space" in error["message"], error
            await client.send(without(P.make_command(3, "goto", target=[0, 0, 1]), "target"))
            error = await client.answer()
            assert_documented(error, "bad_command")
            await client.send(P.make_command(4, "hold"))  # the drone still takes commands
            seq += 1
            await client.send(healthy.frame(seq % n, seq))
            while (msg := await client.answer())["type"] == "error":
                assert msg.get("command_id") != 4, msg
            assert msg["type"] == "pose" and msg["seq"] == seq, msg

    run(go())


@pytest.mark.parametrize("refusal", ["corrupt_image", "bad_sequence"])
def test_too_many_errors_in_a_row_close_the_socket(server, neighbour_keeps_going, refusal):
    """Frames refused for their images or for their order (both by the session's worker)
    count alike."""
    limit = P.LIMITS["max_consecutive_errors"]

    async def go():
        async with fresh_session(server) as client:
            await client.hello()
            if refusal == "bad_sequence":  # every later frame is below this one
                await client.send(frame(limit))
                assert (await client.answer(60))["type"] == "pose"
            for seq in range(limit):
                colour = frame(seq)["colour"]
                if refusal == "corrupt_image":
                    await client.send(frame(seq, colour=colour[: len(colour) // 2]))
                else:
                    await client.send(frame(seq))
                assert_documented(await client.answer(), refusal, seq=seq)
            return await client.close_code()

    assert run(go()) == P.CLOSE_CODES["too_many_errors"]


def test_empty_depth_is_answered_but_never_closes_the_session(server, neighbour_keeps_going):
    """A phone's depth from motion starts empty: more all-zero depth maps than
    max_consecutive_errors are each answered bad_depth, the socket stays open, and the first
    frame with depth gets its pose. Empty depth between other errors does not add to their
    run either."""
    limit = P.LIMITS["max_consecutive_errors"]

    async def go():
        async with fresh_session(server) as client:
            await client.hello()
            seq = 0
            for seq in range(limit + 10):
                await client.send(frame(seq, depth=P.encode_depth(_ZERO)))
                assert_documented(await client.answer(), "bad_depth", seq=seq)
            for _ in range(limit - 1):  # one short of the limit, with empty depth between
                seq += 1
                colour = frame(seq)["colour"]
                await client.send(frame(seq, colour=colour[: len(colour) // 2]))
                assert_documented(await client.answer(), "corrupt_image", seq=seq)
                seq += 1
                await client.send(frame(seq, depth=P.encode_depth(_ZERO)))
                assert_documented(await client.answer(), "bad_depth", seq=seq)
            seq += 1
            await client.send(frame(seq))
            pose = await client.answer(60)
            assert pose["type"] == "pose" and pose["seq"] == seq, pose

    run(go())


def test_a_wrong_depth_scale_that_bypassed_the_codec_is_still_refused_after_decoding():
    """Depth arrives as uint16, so NaN, inf or negative metres can only come from the scale; the
    schema refuses such a scale (invalid_field, above), and the check of the decoded depth in
    metres stands behind it."""
    message = frame(1)
    for scale, why in ((0.0, "not finite"), (-1000.0, "negative"), (1e-3, "is depth_scale")):
        with pytest.raises(P.ProtocolError) as info:
            P.decode_frame_images({**message, "depth_scale": scale}, HELLO)
        assert info.value.code == "bad_depth" and why in info.value.message


# ---- random variants ---------------------------------------------------------------------------

VALUES = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(2**63), 2**64 - 1)
    | st.floats()
    | st.text(max_size=20)
    | st.binary(max_size=64),
    lambda inner: (
        st.lists(inner, max_size=5) | st.dictionaries(st.text(max_size=8), inner, max_size=4)
    ),
    max_leaves=10,
)
VALID = {
    "hello": HELLO,
    "frame": frame(4),
    "command": P.make_command(1, "goto", [0, 0, 1], 1.0),
    "bye": P.make_bye("x"),
    "frame_zlib": frame(4, **{"depth_format": "zlib", "depth": _zlib_depth(DEPTH * 1000)}),
}


@st.composite
def mutated_message(draw) -> dict:
    """A valid message with a field replaced, removed or added, or an image's bytes damaged."""
    message = dict(VALID[draw(st.sampled_from(sorted(VALID)))])
    for _ in range(draw(st.integers(1, 3))):
        key = draw(st.sampled_from(sorted(message)))
        action = draw(st.sampled_from(["replace", "remove", "add", "damage"]))
        if action == "replace":
            message[key] = draw(VALUES)
        elif action == "remove":
            message.pop(key)
        elif action == "add":
            message[draw(st.text(max_size=8))] = draw(VALUES)
        elif isinstance(message.get(key), bytes) and message[key]:
            data = bytearray(message[key])
            for _ in range(draw(st.integers(1, 8))):
                data[draw(st.integers(0, len(data) - 1))] = draw(st.integers(0, 255))
            cut = draw(st.integers(0, len(data)))
            message[key] = bytes(data[:cut] if draw(st.booleans()) else data)
        if not message:
            break
    return message


@st.composite
def mutated_bytes(draw) -> bytes:
    """A valid message's bytes, flipped, cut and spliced."""
    data = bytearray(raw(VALID[draw(st.sampled_from(sorted(VALID)))]))
    for _ in range(draw(st.integers(1, 6))):
        i = draw(st.integers(0, len(data) - 1))
        op = draw(st.sampled_from(["flip", "cut", "insert"]))
        if op == "flip":
            data[i] ^= 1 << draw(st.integers(0, 7))
        elif op == "cut":
            del data[i : i + draw(st.integers(1, 64))]
        else:
            data[i:i] = draw(st.binary(min_size=1, max_size=16))
        if not data:
            return b""
    return bytes(data)


def _decode_all_the_way(data: bytes) -> None:
    """What the server does with a client's message, in-process: decode, check the order (after
    a hello), decode images. Raises only ProtocolError; checks what it returns."""
    message = P.decode(data, direction=P.CLIENT_TO_SERVER, max_bytes=MAX_BYTES)
    order = P.ClientOrder()
    order.check(HELLO)
    order.check(message)
    if message["type"] == "frame":
        colour, depth = P.decode_frame_images(message, HELLO)
        assert colour.shape == (SIZE[1], SIZE[0], 3) and colour.dtype == np.uint8
        assert depth.shape == (SIZE[1], SIZE[0]) and depth.dtype == np.float32
        assert np.isfinite(depth).all() and depth.min() >= 0
        assert depth.max() <= P.LIMITS["max_depth_m"]


@settings(max_examples=200, deadline=None, derandomize=True)
@given(st.one_of(mutated_message().map(raw), mutated_bytes(), st.binary(max_size=200)))
def test_random_variants_raise_nothing_but_documented_protocol_errors(data):
    try:
        _decode_all_the_way(data)
    except P.ProtocolError as exc:
        assert exc.code in P.ERRORS
        P.decode(P.encode(exc.to_message()))  # the answer itself is a valid message


LIVE_EXAMPLES = 15


@settings(
    max_examples=LIVE_EXAMPLES,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(st.one_of(mutated_message().map(raw), mutated_bytes()))
def test_random_variants_through_the_socket_get_documented_answers(server, healthy, data):
    """After a hello, a random variant, then a valid frame: every answer is a valid server
    message; an error is fatal exactly when the socket then closes, with its close code; after
    a non-fatal one the valid frame gets its pose."""
    last = 2**53 - 1  # the final frame's seq: above any a variant may hold

    async def go():
        async with fresh_session(server) as client:
            await client.hello()
            await client.send(data)
            await client.send(frame(last))
            while True:
                try:
                    msg = await client.answer()
                except websockets.ConnectionClosed as closed:  # only a valid bye ends it quietly
                    assert closed.rcvd and closed.rcvd.code == 1000, f"closed with {closed.rcvd}"
                    return
                if msg["type"] == "pose" and msg["seq"] < last:
                    continue  # the variant was a valid frame
                if msg["type"] == "pose":
                    return
                assert msg["type"] == "error", msg
                assert_documented(msg, msg["name"])
                if msg["fatal"]:
                    assert await client.close_code() == P.ERRORS[msg["name"]]["close"]
                    return
                if msg.get("seq") == last:  # a variant took the last seq first
                    return

    started = time.monotonic()
    run(go())
    healthy.wait_for_pose_after(started)


def test_the_healthy_session_never_stalled_and_the_server_still_serves(server, healthy):
    """Last in this module: the neighbour streamed through every case above without an error
    and without a silence longer than MAX_HEALTHY_GAP_S."""
    end = time.monotonic()
    healthy.wait_for_pose_after(end)
    assert not healthy.errors and healthy.close_code is None
    assert len(healthy.pose_times) > 20
    assert healthy.longest_gap() < MAX_HEALTHY_GAP_S, f"longest gap {healthy.longest_gap():.2f} s"
    health = httpx.get(f"{server.url}/healthz").json()
    assert health["status"] == "ok"
