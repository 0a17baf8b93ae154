"""The wire protocol: round trips of every message, every class of bad input, spec consistency."""

from __future__ import annotations

import json
import re
import struct
import zlib

import cv2
import msgpack
import numpy as np
import pytest

from server import protocol as P
from server.errors import DroneSimError
from server.protocol import ProtocolError
from server.protocol.schema import _PY_TYPES
from tests.conftest import missing
from tests.support.paths import REPO, SHARED_DATA

ROOM = SHARED_DATA / "synthetic_room0"
SHARED = REPO / "shared"
ROOM_SCALE = 5000.0  # TUM depth units per metre


@pytest.fixture(scope="module")
def room_frame() -> tuple[np.ndarray, np.ndarray]:
    """Colour RGB uint8 (480, 640, 3) and depth float32 metres (480, 640) of one room frame."""
    if not ROOM.is_dir():
        missing(f"shared data folder {ROOM} is absent")
    _, rgb_name, _, depth_name = (ROOM / "associations.txt").read_text().splitlines()[10].split()
    colour = cv2.cvtColor(cv2.imread(str(ROOM / rgb_name)), cv2.COLOR_BGR2RGB)
    depth = cv2.imread(str(ROOM / depth_name), cv2.IMREAD_UNCHANGED)
    assert depth.dtype == np.uint16
    return colour, depth.astype(np.float32) / np.float32(ROOM_SCALE)


@pytest.fixture(scope="module")
def hello() -> dict:
    return P.make_hello("pytest", [525.0, 525.0, 319.5, 239.5], (640, 480), (640, 480), ROOM_SCALE)


def expect(code: str, fn, *args, **kwargs) -> ProtocolError:
    with pytest.raises(ProtocolError) as info:
        fn(*args, **kwargs)
    assert info.value.code == code, str(info.value)
    return info.value


def small_frame(depth_m: np.ndarray, size=(640, 480), **kwargs) -> dict:
    colour = np.full((size[1], size[0], 3), 128, np.uint8)
    return P.make_frame(7, 1.5, colour, depth_m, **kwargs)


# ---- round trips ------------------------------------------------------------------------------


def example_messages() -> dict[str, dict]:
    rng = np.random.default_rng(0)
    T = np.eye(4)
    T[:3, 3] = [0.5, -1.0, 2.0]
    depth = np.full((24, 32), 1.25, np.float32)
    return {
        "hello": P.make_hello("web/1.0", [500.0, 500.0, 320.0, 240.0], (640, 480), (256, 192)),
        "frame": P.make_frame(3, 12.25, np.zeros((24, 32, 3), np.uint8), depth, "zlib"),
        "command": P.make_command(1, "goto", target=[1.0, 0.5, -2.0], speed=1.5),
        "bye": P.make_bye("user closed the page"),
        "welcome": P.make_welcome("abc123"),
        "pose": P.make_pose(3, 12.25, T, "weak", 57, {"decode": 3.5, "total": 21.0}, 2, True),
        "drone_state": P.make_drone_state(
            4.0,
            T,
            [0.1, 0.0, -0.2],
            "goto",
            command_id=1,
            T_camera_drone=T,
            camera_seq=3,
            clearance=0.4,
            target=[1.0, 0.5, -2.0],
            route=np.zeros((4, 3)),
            damage=12.5,
        ),
        "drone_event": P.make_drone_event("collision", 4.5, [0.1, 0.2, 0.3], "hit a wall", 1),
        "course": P.make_course(
            2,
            "finished",
            "easy",
            17,
            rng.normal(size=(3, 7)),
            ["passed", "missed", "passed"],
            3,
            12.5,
            10.0,
            1,
            0,
            270,
            False,
            rank=1,
            command_id=5,
        ),
        "map_chunk": P.make_map_chunk(
            rng.normal(size=(500, 3)), rng.integers(0, 256, (500, 3)), chunk=4, total_points=2500
        ),
        "map_corrected": P.make_map_corrected(
            2, 120, np.eye(4), [(0, 0, np.eye(4)), (7, 61, np.diag([1.0, -1.0, -1.0, 1.0]))], 3
        ),
        "room": P.make_room(
            ["web/1.0 (Pixel 8)", "web/1.0 (Pixel 7)"],
            1,
            [True, False],
            ["hover", "none"],
            [[0.5, -0.2, 1.5, 0.0, 0.0, 0.0, 1.0], [0.0] * 7],
            [[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0], [0.0] * 7],
            {
                "race": "running",
                "number": 2,
                "starts_in_s": 0.0,
                "gates": 5,
                "passed": [3, 1],
                "missed": [0, 1],
                "time_s": [7.5, 9.25],
                "finished": [False, False],
                "rank": [0, 0],
            },
            [np.array([[0.5, -0.2, 1.5], [1.0, 0.0, 1.4], [2.0, 0.5, 1.2]]), None],
        ),
        "error": P.make_error("corrupt_image", "colour: not a complete JPEG", seq=3),
    }


def test_examples_cover_every_message_type():
    assert set(example_messages()) == set(P.MESSAGES)


@pytest.mark.parametrize("kind", sorted(P.MESSAGES))
def test_every_message_type_round_trips(kind):
    message = example_messages()[kind]
    direction = P.MESSAGES[kind]["direction"]
    assert P.decode(P.encode(message), direction=direction) == message


def test_map_corrected_decodes_to_matrices_and_refuses_bad_keyframes():
    message = example_messages()["map_corrected"]
    decoded = P.decode(P.encode(message), direction=P.SERVER_TO_CLIENT)
    T, keyframes = P.decode_map_corrected(decoded)
    assert np.array_equal(T, np.eye(4)) and set(keyframes) == {0, 7}
    assert keyframes[7][0] == 61 and keyframes[7][1][1, 1] == -1.0
    for bad in ({"id": 1, "seq": 2}, {"id": -1, "seq": 2, "T_world_keyframe": [0.0] * 16}):
        broken = {**message, "keyframes": [bad]}
        with pytest.raises(P.ProtocolError) as exc:
            P.validate(broken, P.SERVER_TO_CLIENT)
        assert exc.value.code == "invalid_field"
    short = {**message, "keyframes": [{"id": 1, "seq": 2, "T_world_keyframe": [0.0] * 15}]}
    with pytest.raises(P.ProtocolError):
        P.validate(short, P.SERVER_TO_CLIENT)


def test_a_rebuilt_maps_preview_and_a_new_surface_come_as_a_chunk_even_when_empty():
    from server.sessions.updates import MapUpdate
    from server.transport.websocket import update_messages

    points = np.zeros((5, 3), np.float32)
    colours = np.zeros((5, 3), np.uint8)
    chunks, nxt = update_messages(MapUpdate(9, points, colours, 5, reset=True), 2, 10)
    assert [c["chunk"] for c in chunks] == [10, 11, 12] and nxt == 13
    assert [c.get("reset") for c in chunks] == [True, None, None]
    empty, _ = update_messages(MapUpdate(9, points[:0], colours[:0], 0, reset=True), 2, 0)
    assert len(empty) == 1 and empty[0]["reset"] is True and empty[0]["count"] == 0
    plain, _ = update_messages(MapUpdate(9, points[:0], colours[:0], 0), 2, 0)
    assert plain == []
    news, _ = update_messages(MapUpdate(9, points[:0], colours[:0], 7, surface=True), 2, 4)
    assert len(news) == 1 and news[0]["surface"] is True and news[0]["count"] == 0
    assert P.decode(P.encode(news[0]))["surface"] is True
    both, _ = update_messages(MapUpdate(9, points, colours, 12, surface=True), 2, 0)
    assert [c["surface"] for c in both] == [True, True, True]


def test_the_updates_enums_are_the_protocols_and_go_out_as_their_values():
    """PoseUpdate.state is a TrackingState and DroneNotice.event a DroneEventKind: each enum
    holds exactly the protocol's values, and an update sends the value, not the member's name."""
    from server.registration.results import TrackingState
    from server.sessions.updates import DroneNotice, PoseUpdate
    from server.simulation.drone_types import DroneEventKind
    from server.transport.websocket import update_messages

    def enum(message: str, field: str) -> set[str]:
        return next(set(f["enum"]) for f in P.MESSAGES[message]["fields"] if f["name"] == field)

    assert {s.value for s in TrackingState} == enum("pose", "state")
    assert {k.value for k in DroneEventKind} == enum("drone_event", "event")
    pose = PoseUpdate(3, 0.2, np.eye(4), TrackingState.WEAK, 40, False, {}, 0, 4)
    notice = DroneNotice(DroneEventKind.GATE_PASSED, 1.5, np.zeros(3), "gate 1 of 5", None)
    for update, field, value in ((pose, "state", "weak"), (notice, "event", "gate_passed")):
        [message], _ = update_messages(update, 2, 0)
        sent = P.decode(P.encode(message))
        assert type(sent[field]) is str and sent[field] == value


@pytest.mark.parametrize("depth_format", ["png", "zlib"])
def test_real_frame_round_trip_is_exact_for_depth(room_frame, hello, depth_format):
    colour, depth = room_frame
    message = P.make_frame(11, 1.0, colour, depth, depth_format, depth_scale=ROOM_SCALE)
    decoded = P.decode(P.encode(message), direction=P.CLIENT_TO_SERVER)
    colour_out, depth_out = P.decode_frame_images(decoded, hello)
    assert colour_out.shape == colour.shape and colour_out.dtype == np.uint8
    mse = np.mean((colour_out.astype(np.float64) - colour) ** 2)
    assert 10 * np.log10(255**2 / mse) > 28  # PSNR in dB; JPEG q=80 of this noisy frame: 31
    assert depth_out.dtype == np.float32
    np.testing.assert_array_equal(depth_out, depth)


def test_millimetre_depth_is_within_half_a_millimetre(room_frame, hello):
    colour, depth = room_frame
    message = P.make_frame(1, 1.0, colour, depth, "png", depth_scale=1000)
    _, depth_out = P.decode_frame_images(message, hello)
    assert np.abs(depth_out - depth).max() <= 0.0005 + 1e-6


def test_depth_smaller_than_colour_keeps_its_own_size(room_frame):
    colour, depth = room_frame
    small = cv2.resize(depth, (320, 240), interpolation=cv2.INTER_NEAREST)
    hello = P.make_hello("t", [525.0, 525.0, 319.5, 239.5], (640, 480), (320, 240), ROOM_SCALE)
    message = P.make_frame(1, 1.0, colour, small, "zlib", depth_scale=ROOM_SCALE)
    colour_out, depth_out = P.decode_frame_images(message, hello)
    assert colour_out.shape == (480, 640, 3) and depth_out.shape == (240, 320)
    assert P.depth_intrinsics(hello) == pytest.approx((262.5, 262.5, 159.5, 119.5))


def test_map_chunk_is_little_endian_float32_and_uint8():
    points = np.array([[1.0, -2.0, 0.5], [3.0, 4.0, 5.0]], np.float32)
    colours = np.array([[255, 0, 10], [1, 2, 3]], np.uint8)
    message = P.make_map_chunk(points, colours)
    assert message["points"][:12] == struct.pack("<3f", 1.0, -2.0, 0.5)
    assert message["colours"] == bytes([255, 0, 10, 1, 2, 3])
    out_points, out_colours = P.decode_map_chunk(P.decode(P.encode(message)))
    np.testing.assert_array_equal(out_points, points)
    np.testing.assert_array_equal(out_colours, colours)


def test_pose_is_row_major():
    T = np.eye(4)
    T[:3, 3] = [1.0, 2.0, 3.0]
    message = P.make_pose(0, 0.0, T, "ok", 100, {}, 0)
    assert [message["T_world_camera"][i] for i in (3, 7, 11)] == [1.0, 2.0, 3.0]
    np.testing.assert_array_equal(P.pose_matrix(message), T)


def test_receiver_ignores_unknown_fields_but_sender_refuses_them():
    message = {**P.make_bye(), "future_field": 1}
    assert P.decode(msgpack.packb(message))["future_field"] == 1
    expect("invalid_field", P.encode, message)


def test_float_fields_accept_integers_as_javascript_sends_them():
    message = {"type": "bye"}
    frame = {**small_frame(np.ones((480, 640))), "timestamp": 2, "depth_scale": 1000}
    for m in (message, frame):
        P.decode(msgpack.packb(m, use_bin_type=True))


# ---- bad input --------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "data",
    [
        b"\xc1",
        b"",
        msgpack.packb({"type": "bye"}) + b"\x00",
        msgpack.packb([1, 2]),
        msgpack.packb({"kind": "bye"}),
        msgpack.packb({1: "bye"}),
        "text frame",
    ],
    ids=["never-used-byte", "empty", "trailing", "list", "no-type", "int-key", "str"],
)
def test_malformed_message(data):
    error = expect("malformed_message", P.decode, data)
    assert error.fatal and error.close_code == P.CLOSE_CODES["protocol_error"]


def test_missing_field():
    frame = small_frame(np.ones((480, 640)))
    del frame["colour"]
    expect("missing_field", P.decode, msgpack.packb(frame, use_bin_type=True))


@pytest.mark.parametrize(
    "field, value",
    [
        ("seq", "7"),
        ("seq", True),
        ("seq", -1),
        ("seq", 1.0),
        ("timestamp", float("nan")),
        ("colour", "not bytes"),
        ("depth_format", "jpeg"),
        ("depth_scale", -1000.0),
    ],
)
def test_wrong_type_or_value(field, value):
    frame = {**small_frame(np.ones((480, 640))), field: value}
    error = expect("invalid_field", P.decode, msgpack.packb(frame, use_bin_type=True))
    if field != "seq":
        assert error.seq == 7  # the server can say which frame it refused


def test_wrong_shape_of_a_pose():
    pose = P.make_pose(0, 0.0, np.eye(4), "ok", 1, {}, 0)
    expect("invalid_field", P.encode, {**pose, "T_world_camera": [0.0] * 15})
    expect("invalid_field", P.encode, {**pose, "timings_ms": {"total": -1.0}})


def test_unknown_type_and_wrong_direction():
    expect("unknown_type", P.decode, msgpack.packb({"type": "teleport"}))
    pose = P.encode(P.make_pose(0, 0.0, np.eye(4), "ok", 1, {}, 0))
    expect("unknown_type", P.decode, pose, direction=P.CLIENT_TO_SERVER)


def test_version_mismatch_is_reported_before_other_fields():
    error = expect("version_mismatch", P.decode, msgpack.packb({"type": "hello", "version": 2}))
    assert error.close_code == P.CLOSE_CODES["version_mismatch"]


@pytest.mark.parametrize(
    "intrinsics",
    [
        [1.0, 1.0, 320.0, 240.0],
        [525.0, 5000.0, 320.0, 240.0],
        [525.0, 525.0, 900.0, 240.0],
        [525.0, 525.0, 320.0, -5.0],
    ],
    ids=["tiny-focal", "fy-absurd", "cx-outside", "cy-negative"],
)
def test_absurd_intrinsics(intrinsics):
    error = expect("bad_intrinsics", P.encode, P.make_hello("t", intrinsics, (640, 480)))
    assert error.close_code == P.CLOSE_CODES["bad_hello"]


@pytest.mark.parametrize(
    "colour_size, depth_size",
    [((8, 6), (8, 6)), ((4096, 3072), (256, 192)), ((640, 480), (256, 256))],
)
def test_bad_image_sizes_in_hello(colour_size, depth_size):
    fx = 0.8 * colour_size[0]
    hello = P.make_hello(
        "t", [fx, fx, colour_size[0] / 2, colour_size[1] / 2], colour_size, depth_size
    )
    expect("bad_image_size", P.encode, hello)


@pytest.mark.parametrize("cut", ["random", "truncated", "png"])
def test_corrupt_jpeg(hello, cut):
    frame = small_frame(np.ones((480, 640)))
    colour = frame["colour"]
    bad = {
        "random": np.random.default_rng(1).bytes(5000),
        "truncated": colour[: len(colour) // 2],
        "png": cv2.imencode(".png", np.zeros((480, 640, 3), np.uint8))[1].tobytes(),
    }[cut]
    error = expect("corrupt_image", P.decode_frame_images, {**frame, "colour": bad}, hello)
    assert not error.fatal and error.seq == 7


@pytest.mark.parametrize("cut", ["truncated", "8-bit", "garbage"])
def test_corrupt_png_depth(hello, cut):
    frame = small_frame(np.ones((480, 640)), depth_format="png")
    bad = {
        "truncated": frame["depth"][: len(frame["depth"]) // 2],
        "8-bit": cv2.imencode(".png", np.ones((480, 640), np.uint8))[1].tobytes(),
        "garbage": b"\x89PNG\r\n\x1a\n" + bytes(100),
    }[cut]
    expect("corrupt_image", P.decode_frame_images, {**frame, "depth": bad}, hello)


def test_corrupt_zlib_depth(hello):
    frame = small_frame(np.ones((480, 640)), depth_format="zlib")
    expect("corrupt_image", P.decode_frame_images, {**frame, "depth": b"not zlib at all"}, hello)
    truncated = frame["depth"][: len(frame["depth"]) // 2]
    expect("corrupt_image", P.decode_frame_images, {**frame, "depth": truncated}, hello)


@pytest.mark.parametrize("depth_format", ["png", "zlib"])
def test_depth_size_contradicting_hello(hello, depth_format):
    frame = small_frame(np.ones((240, 320)), depth_format=depth_format)
    expect("size_mismatch", P.decode_frame_images, frame, hello)


def test_zlib_bomb_is_refused_without_inflating_it(hello):
    frame = small_frame(np.ones((480, 640)), depth_format="zlib")
    bomb = zlib.compress(bytes(200_000_000), 9)  # 200 MB of zeros in about 200 kB
    expect("size_mismatch", P.decode_frame_images, {**frame, "depth": bomb}, hello)


def test_colour_size_contradicting_hello(hello):
    frame = small_frame(np.ones((480, 640)))
    frame["colour"] = P.encode_jpeg(np.zeros((240, 320, 3), np.uint8))
    expect("size_mismatch", P.decode_frame_images, frame, hello)


def test_bad_depth_scale_gives_negative_or_huge_depth(room_frame, hello):
    colour, depth = room_frame
    frame = P.make_frame(1, 1.0, colour, depth, "zlib", depth_scale=ROOM_SCALE)
    expect("bad_depth", P.decode_frame_images, {**frame, "depth_scale": -ROOM_SCALE}, hello)
    expect("bad_depth", P.decode_frame_images, {**frame, "depth_scale": 0.0}, hello)
    # Scale 1 passes the schema, but the depth would be thousands of metres.
    huge = P.decode(P.encode({**frame, "depth_scale": 1.0}))
    error = expect("bad_depth", P.decode_frame_images, huge, hello)
    assert "depth_scale" in error.message


def test_all_zero_depth_means_below_one_percent_valid(hello):
    depth = np.zeros((480, 640), np.float32)
    expect("bad_depth", P.decode_frame_images, small_frame(depth), hello)
    depth.reshape(-1)[: int(0.005 * depth.size)] = 2.0  # 0.5 % valid: still all-zero
    expect("bad_depth", P.decode_frame_images, small_frame(depth), hello)
    depth.reshape(-1)[: int(0.02 * depth.size)] = 2.0  # 2 % valid: accepted
    P.decode_frame_images(small_frame(depth), hello)


def test_non_finite_depth_is_sent_as_no_measurement(hello):
    depth = np.ones((480, 640), np.float32)
    depth[:10] = np.nan
    depth[10:20] = -1.0
    _, out = P.decode_frame_images(small_frame(depth, depth_format="zlib"), hello)
    assert (out[:20] == 0).all() and (out[20:] == 1).all()


def test_oversized_payload_is_rejected_before_unpacking(monkeypatch):
    def unpack_must_not_run(*args, **kwargs):
        raise AssertionError("unpacked an oversized message")

    monkeypatch.setattr(msgpack, "unpackb", unpack_must_not_run)
    data = bytes(P.LIMITS["max_message_bytes"] + 1)
    error = expect("message_too_big", P.decode, data)
    assert error.close_code == P.CLOSE_CODES["message_too_big"]
    expect("message_too_big", P.decode, bytes(2000), max_bytes=1024)


def test_oversized_message_is_not_encoded():
    big = P.make_map_chunk(np.zeros((16384, 3)), np.zeros((16384, 3)))
    expect("message_too_big", P.encode, big, max_bytes=100_000)


def test_order_rules_of_a_client():
    """By the messages' types: a frame's seq is the session worker's to order (bad_sequence,
    tests/server/test_bad_input.py)."""
    order = P.ClientOrder()
    expect("unexpected_message", order.check, "frame")  # frame before hello
    expect("unexpected_message", order.check, "command")
    order.check("hello")
    expect("unexpected_message", order.check, "hello")  # second hello
    order.check("frame")
    order.check("frame")
    order.check("command")
    assert not order.closed
    order.check("bye")
    assert order.closed
    expect("unexpected_message", order.check, "frame")  # anything after bye
    expect("unexpected_message", order.check, "bye")


def test_a_bool_seq_is_no_seq_in_the_error():
    """True is an int to Python, not to the protocol: the error must not carry it (it could not
    be encoded)."""
    error = expect("invalid_field", P.validate, small_frame(np.ones((480, 640))) | {"seq": True})
    assert error.seq is None
    P.encode(error.to_message())


def test_goto_without_target_is_a_bad_command():
    error = expect("bad_command", P.encode, P.make_command(1, "goto"))
    assert not error.fatal


def test_protocol_error_is_a_project_error_and_becomes_an_error_message():
    error = ProtocolError("bad_depth", "all-zero depth", seq=4)
    assert isinstance(error, DroneSimError)
    message = P.decode(P.encode(error.to_message()))
    assert (message["code"], message["name"], message["seq"]) == (202, "bad_depth", 4)
    assert P.make_error(202, "x")["name"] == "bad_depth"
    with pytest.raises(ValueError):
        ProtocolError("no_such_code", "x")


# ---- the definition itself --------------------------------------------------------------------


def test_definition_is_well_formed():
    spec = json.loads((SHARED / "protocol.json").read_text())
    assert spec["version"] == P.VERSION == 1
    known = {
        "name",
        "type",
        "required",
        "unit",
        "description",
        "min",
        "max",
        "enum",
        "length",
        "min_length",
        "max_length",
        "items",
        "values",
    }
    for kind, message in spec["messages"].items():
        assert message["direction"] in (P.CLIENT_TO_SERVER, P.SERVER_TO_CLIENT), kind
        for field in message["fields"]:
            assert set(field) <= known and field["type"] in _PY_TYPES, (kind, field)
    codes = [e["code"] for e in spec["errors"]]
    closes = {c["code"] for c in spec["close_codes"]}
    assert len(set(codes)) == len(codes)
    assert all(4000 <= c <= 4999 for c in closes)
    for error in spec["errors"]:
        assert (error["close"] in closes) if error["fatal"] else error["close"] is None, error
    assert set(spec["limits"]) == set(spec["limits_description"])


def test_markdown_documents_every_message_field_error_and_close_code():
    text = (SHARED / "PROTOCOL.md").read_text()
    sections = dict(re.findall(r"^### `(\w+)`\n(.*?)(?=^#{2,3} )", text, re.S | re.M))
    for kind, message in P.MESSAGES.items():
        assert kind in sections, f"PROTOCOL.md has no section ### `{kind}`"
        for field in message["fields"]:
            assert f"`{field['name']}`" in sections[kind], (kind, field["name"])
    for error in P.SPEC["errors"]:
        assert re.search(rf"`{error['name']}`\s*\|\s*{error['code']}\b", text), error["name"]
    for close in P.SPEC["close_codes"]:
        assert re.search(rf"{close['code']}\s*\|\s*`{close['name']}`", text), close["name"]
    for name in P.LIMITS:
        assert f"`{name}`" in text, name


def test_zero_gravity_is_refused():
    hello = P.make_hello("t", [500.0, 500.0, 320.0, 240.0], (640, 480), gravity=[0.0, 9.8, 0.1])
    assert P.decode(P.encode(hello))["gravity"] == [0.0, 9.8, 0.1]
    error = expect("invalid_field", P.encode, {**hello, "gravity": [0.0, 0.0, 0.0]})
    assert "gravity" in error.message


def test_each_drone_command_needs_its_own_field():
    for name, field in [("goto", "target"), ("goto_pixel", "pixel"), ("sticks", "sticks")]:
        error = expect("bad_command", P.encode, P.make_command(1, name))
        assert field in str(error)
    sticks = P.make_command(2, "sticks", sticks=[0.0, 0.5, 1.0, -1.0])
    assert P.decode(P.encode(sticks))["sticks"] == [0.0, 0.5, 1.0, -1.0]
    expect("invalid_field", P.encode, {**sticks, "sticks": [0.0, 0.0, 1.5, 0.0]})


@pytest.mark.parametrize(
    "command, named",
    [
        ({"type": "command", "id": 8, "name": "goto"}, 8),  # no target
        ({"type": "command", "id": 9, "name": "fly_away"}, 9),  # no such command
        ({"type": "command", "id": -1, "name": "goto"}, None),  # an id the error cannot carry
        ({"type": "command", "name": "goto"}, None),  # no id at all
    ],
)
def test_a_refused_command_names_its_id_when_it_can_be_read(command, named):
    with pytest.raises(P.ProtocolError) as refused:
        P.decode(msgpack.packb(command), direction=P.CLIENT_TO_SERVER)
    error = refused.value.to_message()
    assert error.get("command_id") == named, error
    P.validate(error, P.SERVER_TO_CLIENT)  # what the client gets is itself valid


def test_every_close_code_says_whether_a_client_reconnects():
    """protocol.json tells clients (the page reads it) after which close codes to reconnect:
    never (final: a new session or a fix is needed), when active (on the next frame or command),
    when asked (the user's own action) or retry (with back-off)."""
    ways = {c["name"]: c.get("reconnect") for c in P.SPEC["close_codes"]}
    assert set(ways.values()) <= {"never", "when_active", "when_asked", "retry"}, ways
    assert ways["version_mismatch"] == ways["unauthorized"] == ways["session_failed"] == "never"
    assert ways["idle_timeout"] == "when_active" and ways["session_taken_over"] == "when_asked"


def test_a_room_message_carries_a_race_and_routes_together():
    room = P.decode(P.encode(example_messages()["room"]))
    assert room["race"] == "running" and room["race_rank"] == [0, 0]
    assert room["route_lengths"] == [3, 0] and len(room["routes"]) == 9
