"""Wire protocol codec: msgpack messages as defined once in ``shared/protocol.json``.

``encode``/``decode`` check every message against that definition and raise ``ProtocolError``
with one of its error code names. The ``make_*`` helpers build messages from numpy data
(images are JPEG / PNG / zlib encoded, map points packed little-endian); ``decode_frame_images``
turns a frame back into an RGB image and a depth map in metres. See ``shared/PROTOCOL.md``.
"""

from __future__ import annotations

import json
import math
import zlib
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import cv2
import msgpack
import numpy as np

from server.errors import DroneSimError

PROTOCOL_PATH = Path(__file__).resolve().parents[2] / "shared" / "protocol.json"
SPEC: dict = json.loads(PROTOCOL_PATH.read_text())
VERSION: int = SPEC["version"]
LIMITS: dict = SPEC["limits"]
MESSAGES: dict = SPEC["messages"]
ERRORS: dict[str, dict] = {e["name"]: e for e in SPEC["errors"]}
_MAX_SEQ = next(f["max"] for f in MESSAGES["frame"]["fields"] if f["name"] == "seq")
ERROR_NAMES: dict[int, str] = {e["code"]: e["name"] for e in SPEC["errors"]}
CLOSE_CODES: dict[str, int] = {c["name"]: c["code"] for c in SPEC["close_codes"]}
CLIENT_TO_SERVER = "client_to_server"
SERVER_TO_CLIENT = "server_to_client"

PNG_COMPRESSION = 3  # zlib level inside the PNG; 1-3 are near the size of 9 for depth, much faster
ZLIB_LEVEL = 6  # zlib's default, what browsers' CompressionStream("deflate") uses
_PY_TYPES = {
    "int": int,
    "float": (int, float),
    "str": str,
    "bytes": (bytes, bytearray),
    "bool": bool,
    "list": (list, tuple),
    "map": dict,
}
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_IEND = b"\x00\x00\x00\x00IEND\xaeB`\x82"


class ProtocolError(DroneSimError):
    """A message breaks the protocol. ``code`` is an error name from protocol.json."""

    def __init__(self, code: str, message: str, *, seq: int | None = None) -> None:
        if code not in ERRORS:
            raise ValueError(f"unknown protocol error code {code!r}; known: {sorted(ERRORS)}")
        super().__init__(f"{code}: {message}")
        self.code, self.message, self.seq = code, message, seq

    @property
    def number(self) -> int:
        return ERRORS[self.code]["code"]

    @property
    def fatal(self) -> bool:
        return ERRORS[self.code]["fatal"]

    @property
    def close_code(self) -> int | None:
        """The WebSocket close code that follows a fatal error, None for a non-fatal one."""
        return ERRORS[self.code]["close"]

    def to_message(self) -> dict:
        """The error for the client; a seq that is itself invalid (e.g. negative) is left out,
        as the error message could not carry it."""
        valid = isinstance(self.seq, int) and 0 <= self.seq <= _MAX_SEQ
        return make_error(self.code, self.message, seq=self.seq if valid else None)


# ---- validation against protocol.json ---------------------------------------------------------


def _check_value(value: Any, spec: Mapping, where: str) -> None:
    kind = spec["type"]
    if (isinstance(value, bool) and kind != "bool") or not isinstance(value, _PY_TYPES[kind]):
        raise ProtocolError("invalid_field", f"{where} must be {kind}, got {type(value).__name__}")
    if kind == "float" and not math.isfinite(value):
        raise ProtocolError("invalid_field", f"{where} must be finite, got {value}")
    if "min" in spec and value < spec["min"]:
        raise ProtocolError("invalid_field", f"{where} = {value} is below {spec['min']}")
    if "max" in spec and value > spec["max"]:
        raise ProtocolError("invalid_field", f"{where} = {value} is above {spec['max']}")
    if "enum" in spec and value not in spec["enum"]:
        raise ProtocolError("invalid_field", f"{where} = {value!r} is not one of {spec['enum']}")
    if kind in ("str", "bytes", "list", "map"):
        n = len(value)
        if "length" in spec and n != spec["length"]:
            raise ProtocolError("invalid_field", f"{where} has length {n}, need {spec['length']}")
        if n < spec.get("min_length", 0) or n > spec.get("max_length", math.inf):
            raise ProtocolError("invalid_field", f"{where} has length {n}, outside the limits")
    if kind == "list" and "items" in spec:
        for i, item in enumerate(value):
            _check_value(item, spec["items"], f"{where}[{i}]")
    if kind == "map":
        for key, item in value.items():
            if not isinstance(key, str):
                raise ProtocolError("invalid_field", f"{where} keys must be str, got {key!r}")
            if "values" in spec:
                _check_value(item, spec["values"], f"{where}.{key}")


def _check_hello(msg: Mapping) -> None:
    """What the schema cannot say: plausible image sizes and intrinsics."""
    lo, hi = LIMITS["min_image_side"], LIMITS["max_image_side"]
    for key in ("colour_size", "depth_size"):
        if not all(lo <= side <= hi for side in msg[key]):
            raise ProtocolError("bad_image_size", f"{key} {msg[key]} outside [{lo}, {hi}] px")
    (cw, ch), (dw, dh) = msg["colour_size"], msg["depth_size"]
    if abs((dw / dh) / (cw / ch) - 1) > LIMITS["max_aspect_difference"]:
        raise ProtocolError(
            "bad_image_size", f"depth {dw}x{dh} and colour {cw}x{ch} have different aspect ratios"
        )
    fx, fy, cx, cy = msg["intrinsics"]
    f_lo, f_hi = LIMITS["min_focal_ratio"], LIMITS["max_focal_ratio"]
    if not (f_lo * cw <= fx <= f_hi * cw and f_lo * ch <= fy <= f_hi * ch):
        raise ProtocolError(
            "bad_intrinsics",
            f"fx {fx}, fy {fy} implausible for {cw}x{ch}: need fx/width and fy/height "
            f"in [{f_lo}, {f_hi}]",
        )
    if max(fx, fy) / min(fx, fy) > LIMITS["max_focal_aspect"]:
        raise ProtocolError("bad_intrinsics", f"fx {fx} and fy {fy} differ too much")
    if "gravity" in msg and not np.linalg.norm(msg["gravity"]) > 1e-6:
        raise ProtocolError("invalid_field", "gravity must be a non-zero vector")
    if not (0 <= cx <= cw and 0 <= cy <= ch):
        raise ProtocolError("bad_intrinsics", f"principal point ({cx}, {cy}) outside {cw}x{ch}")


_COMMAND_NEEDS = {"goto": "target", "goto_pixel": "pixel", "sticks": "sticks"}


def _check_command(msg: Mapping) -> None:
    needed = _COMMAND_NEEDS.get(msg["name"])
    if needed and needed not in msg:
        raise ProtocolError("bad_command", f"{msg['name']} needs the field {needed!r}")


def _check_map_chunk(msg: Mapping) -> None:
    n = msg["count"]
    if n > LIMITS["max_map_chunk_points"]:
        raise ProtocolError("invalid_field", f"map_chunk has {n} points, more than the limit")
    if len(msg["points"]) != 12 * n or len(msg["colours"]) != 3 * n:
        raise ProtocolError("invalid_field", f"map_chunk points/colours lengths do not match {n}")


def _check_error(msg: Mapping) -> None:
    if ERROR_NAMES.get(msg["code"]) != msg["name"]:
        raise ProtocolError("invalid_field", f"error code {msg['code']} is not {msg['name']!r}")


_SEMANTIC_CHECKS = {
    "hello": _check_hello,
    "command": _check_command,
    "map_chunk": _check_map_chunk,
    "error": _check_error,
}


def validate(message: Any, direction: str | None = None, *, strict: bool = False) -> dict:
    """Check a message against protocol.json and return it.

    direction: ``CLIENT_TO_SERVER`` or ``SERVER_TO_CLIENT`` to refuse messages the other side
    sends (as unknown_type); None accepts both. strict: refuse fields the spec does not list
    (used when encoding; a receiver ignores them for forward compatibility).
    """
    if not isinstance(message, dict) or not isinstance(message.get("type"), str):
        raise ProtocolError("malformed_message", "a message is a map with a str 'type' field")
    kind = message["type"]
    spec = MESSAGES.get(kind)
    if spec is None or (direction is not None and spec["direction"] != direction):
        raise ProtocolError("unknown_type", f"no {direction or 'protocol'} message {kind!r}")
    seq = message.get("seq") if isinstance(message.get("seq"), int) else None
    # A hello from another version may have other fields: report the version first.
    version = message.get("version")
    if kind == "hello" and isinstance(version, int) and version != VERSION:
        raise ProtocolError("version_mismatch", f"client speaks {version}, server {VERSION}")
    try:
        for field in spec["fields"]:
            if field["name"] in message:
                _check_value(message[field["name"]], field, f"{kind}.{field['name']}")
            elif field["required"]:
                raise ProtocolError("missing_field", f"{kind} needs field {field['name']!r}")
        if strict:
            extra = set(message) - {f["name"] for f in spec["fields"]} - {"type"}
            if extra:
                raise ProtocolError("invalid_field", f"{kind} has unknown fields {sorted(extra)}")
        if kind in _SEMANTIC_CHECKS:
            _SEMANTIC_CHECKS[kind](message)
    except ProtocolError as exc:
        exc.seq = seq
        raise
    return message


def encode(message: dict, *, max_bytes: int | None = None) -> bytes:
    """Validate (strictly) and pack one message; raises ProtocolError."""
    validate(message, strict=True)
    data = msgpack.packb(message, use_bin_type=True)
    limit = LIMITS["max_message_bytes"] if max_bytes is None else max_bytes
    if len(data) > limit:
        raise ProtocolError("message_too_big", f"{len(data)} bytes, limit {limit}")
    return data


def decode(data: bytes, *, direction: str | None = None, max_bytes: int | None = None) -> dict:
    """Unpack and validate one message; the size limit is checked before unpacking."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise ProtocolError("malformed_message", f"need binary data, got {type(data).__name__}")
    limit = LIMITS["max_message_bytes"] if max_bytes is None else max_bytes
    if len(data) > limit:
        raise ProtocolError("message_too_big", f"{len(data)} bytes, limit {limit}")
    try:
        message = msgpack.unpackb(data, raw=False, strict_map_key=True)
    except (ValueError, TypeError, OverflowError, msgpack.UnpackException) as exc:
        raise ProtocolError("malformed_message", f"not one msgpack object: {exc}") from exc
    return validate(message, direction)


class ClientOrder:
    """The order rules of a client's messages: hello first and once, then frames with
    increasing seq, nothing after bye. ``check`` raises unexpected_message or bad_sequence."""

    def __init__(self) -> None:
        self.hello: dict | None = None
        self.last_seq: int | None = None
        self.closed = False

    def check(self, message: Mapping) -> None:
        kind = message["type"]
        if self.closed:
            raise ProtocolError("unexpected_message", f"{kind} after bye")
        if kind == "hello":
            if self.hello is not None:
                raise ProtocolError("unexpected_message", "second hello")
            self.hello = dict(message)
            return
        if self.hello is None:
            raise ProtocolError("unexpected_message", f"{kind} before hello")
        if kind == "bye":
            self.closed = True
        elif kind == "frame":
            seq = message["seq"]
            if self.last_seq is not None and seq <= self.last_seq:
                raise ProtocolError(
                    "bad_sequence", f"frame seq {seq} after seq {self.last_seq}", seq=seq
                )
            self.last_seq = seq


# ---- message builders -------------------------------------------------------------------------


def _message(kind: str, **fields: Any) -> dict:
    return {"type": kind, **{k: v for k, v in fields.items() if v is not None}}


def _floats(values: Any, n: int, name: str) -> list[float]:
    flat = np.asarray(values, dtype=np.float64).reshape(-1)
    if flat.size != n:
        raise ProtocolError("invalid_field", f"{name} needs {n} numbers, got {flat.size}")
    return flat.tolist()


def make_hello(
    client_name: str,
    intrinsics: Sequence[float],
    colour_size: Sequence[int],
    depth_size: Sequence[int] | None = None,
    depth_scale: float = 1000.0,
    version: int = VERSION,
    gravity: Sequence[float] | None = None,
) -> dict:
    """intrinsics: fx, fy, cx, cy of the colour image (px); sizes (width, height) px;
    depth_size defaults to colour_size; depth_scale: depth units per metre; gravity: its
    direction in the first camera's frame (None: the server assumes +y)."""
    depth_size = colour_size if depth_size is None else depth_size
    return _message(
        "hello",
        version=int(version),
        client_name=client_name,
        intrinsics=_floats(intrinsics, 4, "intrinsics"),
        colour_size=[int(v) for v in colour_size],
        depth_size=[int(v) for v in depth_size],
        depth_scale=float(depth_scale),
        gravity=None if gravity is None else _floats(gravity, 3, "gravity"),
    )


def encode_depth(
    depth_m: np.ndarray, depth_format: str = "png", depth_scale: float = 1000.0
) -> bytes:
    """Depth (H, W) metres -> uint16 units of 1/depth_scale m, PNG or zlib bytes.

    Non-finite, non-positive and unrepresentable (> 65535 units) depths become 0 (no measurement).
    """
    depth = np.asarray(depth_m, dtype=np.float64)
    if depth.ndim != 2:
        raise ProtocolError("invalid_field", f"depth must be (H, W), got shape {depth.shape}")
    units = np.rint(np.nan_to_num(depth * depth_scale, nan=0.0, posinf=0.0, neginf=0.0))
    units[(units < 0) | (units > 65535)] = 0
    u16 = units.astype("<u2")
    if depth_format == "png":
        ok, buf = cv2.imencode(".png", u16, [cv2.IMWRITE_PNG_COMPRESSION, PNG_COMPRESSION])
        if not ok:
            raise ProtocolError("invalid_field", "depth does not encode as PNG")
        return buf.tobytes()
    if depth_format == "zlib":
        return zlib.compress(u16.tobytes(), ZLIB_LEVEL)
    raise ProtocolError("invalid_field", f"depth_format must be png or zlib, got {depth_format!r}")


def encode_jpeg(colour_rgb: np.ndarray, quality: int = 80) -> bytes:
    """(H, W, 3) uint8 RGB -> baseline JPEG bytes."""
    if colour_rgb.ndim != 3 or colour_rgb.shape[2] != 3 or colour_rgb.dtype != np.uint8:
        raise ProtocolError(
            "invalid_field", f"colour must be (H, W, 3) uint8, got {colour_rgb.shape}"
        )
    bgr = cv2.cvtColor(colour_rgb, cv2.COLOR_RGB2BGR)
    ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ProtocolError("invalid_field", "colour does not encode as JPEG")
    return buf.tobytes()


def make_frame(
    seq: int,
    timestamp: float,
    colour_rgb: np.ndarray,
    depth_m: np.ndarray,
    depth_format: str = "png",
    jpeg_quality: int = 80,
    depth_scale: float = 1000.0,
) -> dict:
    """A frame message: colour (H, W, 3) uint8 RGB as JPEG, depth (h, w) metres as uint16."""
    return _message(
        "frame",
        seq=int(seq),
        timestamp=float(timestamp),
        colour=encode_jpeg(colour_rgb, jpeg_quality),
        depth=encode_depth(depth_m, depth_format, depth_scale),
        depth_format=depth_format,
        depth_scale=float(depth_scale),
    )


def make_command(
    command_id: int,
    name: str,
    target: Sequence[float] | None = None,
    speed: float | None = None,
    *,
    pixel: Sequence[float] | None = None,
    seq: int | None = None,
    sticks: Sequence[float] | None = None,
) -> dict:
    """target: world [x, y, z] metres (goto); pixel: [u, v] of frame seq (goto_pixel);
    sticks: [throttle, yaw, pitch, roll] in -1..1 (sticks)."""
    return _message(
        "command",
        id=int(command_id),
        name=name,
        target=None if target is None else _floats(target, 3, "target"),
        pixel=None if pixel is None else _floats(pixel, 2, "pixel"),
        seq=None if seq is None else int(seq),
        sticks=None if sticks is None else _floats(sticks, 4, "sticks"),
        speed=None if speed is None else float(speed),
    )


def make_bye(reason: str | None = None) -> dict:
    return _message("bye", reason=reason)


def make_welcome(
    session_id: str,
    max_in_flight: int = LIMITS["max_in_flight"],
    max_message_bytes: int = LIMITS["max_message_bytes"],
    map_chunk_max_points: int = LIMITS["max_map_chunk_points"],
) -> dict:
    return _message(
        "welcome",
        version=VERSION,
        session_id=session_id,
        max_in_flight=int(max_in_flight),
        max_message_bytes=int(max_message_bytes),
        map_chunk_max_points=int(map_chunk_max_points),
    )


def make_pose(
    seq: int,
    timestamp: float,
    T_world_camera: np.ndarray,
    state: str,
    inliers: int,
    timings_ms: Mapping[str, float],
    dropped: int,
    keyframe: bool | None = None,
) -> dict:
    """T_world_camera: 4x4 (metres), sent row-major; state: ok / weak / lost (or TrackingState)."""
    return _message(
        "pose",
        seq=int(seq),
        timestamp=float(timestamp),
        T_world_camera=_floats(T_world_camera, 16, "T_world_camera"),
        state=str(getattr(state, "value", state)),
        inliers=int(inliers),
        timings_ms={str(k): float(v) for k, v in timings_ms.items()},
        dropped=int(dropped),
        keyframe=None if keyframe is None else bool(keyframe),
    )


def make_drone_state(
    timestamp: float,
    T_world_drone: np.ndarray,
    velocity: Sequence[float],
    mode: str,
    command_id: int | None = None,
    *,
    T_camera_drone: np.ndarray | None = None,
    camera_seq: int | None = None,
    clearance: float | None = None,
    target: Sequence[float] | None = None,
    route: np.ndarray | None = None,
) -> dict:
    """Transforms 4x4 (metres, sent row-major); route (N, 3) world metres, at most 512 points."""
    return _message(
        "drone_state",
        timestamp=float(timestamp),
        T_world_drone=_floats(T_world_drone, 16, "T_world_drone"),
        T_camera_drone=None
        if T_camera_drone is None
        else _floats(T_camera_drone, 16, "T_camera_drone"),
        camera_seq=None if camera_seq is None else int(camera_seq),
        velocity=_floats(velocity, 3, "velocity"),
        mode=str(getattr(mode, "value", mode)),
        clearance=None if clearance is None else float(clearance),
        target=None if target is None else _floats(target, 3, "target"),
        route=None if route is None else np.asarray(route, dtype=np.float64).ravel().tolist(),
        command_id=None if command_id is None else int(command_id),
    )


def make_drone_event(
    event: str,
    timestamp: float,
    position: Sequence[float],
    message: str,
    command_id: int | None = None,
) -> dict:
    return _message(
        "drone_event",
        event=str(getattr(event, "value", event)),
        timestamp=float(timestamp),
        position=_floats(position, 3, "position"),
        message=message[:1024],
        command_id=None if command_id is None else int(command_id),
    )


def make_map_chunk(
    points: np.ndarray,
    colours: np.ndarray,
    chunk: int = 0,
    total_points: int | None = None,
    reset: bool | None = None,
) -> dict:
    """points (N, 3) metres -> N*12 bytes float32 LE; colours (N, 3) uint8 RGB -> N*3 bytes."""
    pts = np.ascontiguousarray(points, dtype="<f4")
    rgb = np.ascontiguousarray(colours, dtype=np.uint8)
    if pts.ndim != 2 or pts.shape[1] != 3 or rgb.shape != pts.shape:
        raise ProtocolError(
            "invalid_field", f"need (N, 3) points and colours, got {pts.shape} and {rgb.shape}"
        )
    n = len(pts)
    return _message(
        "map_chunk",
        chunk=int(chunk),
        count=n,
        points=pts.tobytes(),
        colours=rgb.tobytes(),
        total_points=n if total_points is None else int(total_points),
        reset=reset,
    )


def make_error(
    code: str | int,
    message: str,
    *,
    seq: int | None = None,
    command_id: int | None = None,
    nearest: Sequence[float] | None = None,
) -> dict:
    """code: an error name ('corrupt_image') or its number (200)."""
    name = ERROR_NAMES.get(code, code) if isinstance(code, int) else code
    if name not in ERRORS:
        raise ValueError(f"unknown protocol error code {code!r}")
    entry = ERRORS[name]
    return _message(
        "error",
        code=entry["code"],
        name=name,
        message=message[:1024],
        fatal=entry["fatal"],
        seq=seq,
        command_id=command_id,
        nearest=None if nearest is None else _floats(nearest, 3, "nearest"),
    )


# ---- message readers --------------------------------------------------------------------------


def pose_matrix(message: Mapping, key: str = "T_world_camera") -> np.ndarray:
    """The 4x4 float64 transform of a pose (or drone_state with key='T_world_drone')."""
    return np.asarray(message[key], dtype=np.float64).reshape(4, 4)


def decode_map_chunk(message: Mapping) -> tuple[np.ndarray, np.ndarray]:
    """-> points (N, 3) float32 metres, colours (N, 3) uint8 RGB."""
    points = np.frombuffer(message["points"], dtype="<f4").reshape(-1, 3).astype(np.float32)
    colours = np.frombuffer(message["colours"], dtype=np.uint8).reshape(-1, 3).copy()
    return points, colours


def depth_intrinsics(hello: Mapping) -> tuple[float, float, float, float]:
    """fx, fy, cx, cy of the depth image: the colour ones scaled to depth_size (pixel centres)."""
    fx, fy, cx, cy = hello["intrinsics"]
    (cw, ch), (dw, dh) = hello["colour_size"], hello["depth_size"]
    sx, sy = dw / cw, dh / ch
    return fx * sx, fy * sy, (cx + 0.5) * sx - 0.5, (cy + 0.5) * sy - 0.5


def _jpeg_size(data: bytes) -> tuple[int, int]:
    """(width, height) from the JPEG's frame header, without decoding; raises ValueError."""
    if data[:3] != b"\xff\xd8\xff" or data.rstrip(b"\x00")[-2:] != b"\xff\xd9":
        raise ValueError("not a complete JPEG (no start or end marker)")
    i = 2
    while i + 4 <= len(data):
        if data[i] != 0xFF:
            raise ValueError(f"bad JPEG marker at byte {i}")
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
        elif marker == 0x01 or 0xD0 <= marker <= 0xD7:  # markers without a length
            i += 2
        elif 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC) and i + 9 <= len(data):
            return int.from_bytes(data[i + 7 : i + 9], "big"), int.from_bytes(
                data[i + 5 : i + 7], "big"
            )
        else:
            i += 2 + int.from_bytes(data[i + 2 : i + 4], "big")
    raise ValueError("JPEG has no frame header")


def _png_size(data: bytes) -> tuple[int, int]:
    """(width, height) of a complete 16-bit greyscale PNG, from its header; raises ValueError."""
    if data[:8] != _PNG_SIGNATURE or data[12:16] != b"IHDR" or len(data) < 33:
        raise ValueError("not a PNG")
    if data[24] != 16 or data[25] != 0:
        raise ValueError(f"depth PNG must be 16-bit greyscale, got {data[24]}-bit type {data[25]}")
    if not data.endswith(_PNG_IEND):
        raise ValueError("truncated PNG (no IEND chunk)")
    return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")


def _decode_colour(data: bytes, size: tuple[int, int], seq: int | None) -> np.ndarray:
    try:
        found = _jpeg_size(bytes(data))
    except ValueError as exc:
        raise ProtocolError("corrupt_image", f"colour: {exc}", seq=seq) from exc
    if found != size:
        raise ProtocolError("size_mismatch", f"colour is {found}, hello said {size}", seq=seq)
    bgr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if bgr is None or bgr.shape[1::-1] != size:
        raise ProtocolError("corrupt_image", "colour JPEG does not decode", seq=seq)
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def _decode_depth_units(
    data: bytes, fmt: str, size: tuple[int, int], seq: int | None
) -> np.ndarray:
    width, height = size
    if fmt == "png":
        try:
            found = _png_size(bytes(data))
        except ValueError as exc:
            raise ProtocolError("corrupt_image", f"depth: {exc}", seq=seq) from exc
        if found != size:
            raise ProtocolError("size_mismatch", f"depth is {found}, hello said {size}", seq=seq)
        u16 = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        if u16 is None or u16.dtype != np.uint16 or u16.shape != (height, width):
            raise ProtocolError("corrupt_image", "depth PNG does not decode", seq=seq)
        return u16
    expected = 2 * width * height  # zlib: bound the output, a small stream can inflate to GBs
    inflater = zlib.decompressobj()
    try:
        raw = inflater.decompress(data, expected + 1)
    except zlib.error as exc:
        raise ProtocolError("corrupt_image", f"depth zlib: {exc}", seq=seq) from exc
    if len(raw) > expected or inflater.unconsumed_tail:
        raise ProtocolError("size_mismatch", f"depth inflates past {width}x{height}", seq=seq)
    if not inflater.eof:
        raise ProtocolError("corrupt_image", "depth zlib stream is truncated", seq=seq)
    if len(raw) != expected:
        raise ProtocolError(
            "size_mismatch",
            f"depth has {len(raw) // 2} values, hello said {width}x{height}",
            seq=seq,
        )
    return np.frombuffer(raw, dtype="<u2").reshape(height, width)


def decode_frame_images(message: Mapping, hello: Mapping) -> tuple[np.ndarray, np.ndarray]:
    """-> colour (H, W, 3) uint8 RGB at colour_size, depth (h, w) float32 metres at depth_size.

    Raises ProtocolError: corrupt_image, size_mismatch (against the hello), or bad_depth when
    the depth in metres is non-finite, negative, above max_depth_m (a wrong depth_scale), or
    all-zero: fewer than min_valid_depth_fraction of its pixels hold a measurement (> 0).
    """
    seq = message.get("seq")
    colour = _decode_colour(message["colour"], tuple(hello["colour_size"]), seq)
    units = _decode_depth_units(
        message["depth"], message["depth_format"], tuple(hello["depth_size"]), seq
    )
    scale = message.get("depth_scale", hello["depth_scale"])
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = units.astype(np.float32) / np.float32(scale)
    if not np.isfinite(depth).all():
        raise ProtocolError("bad_depth", f"depth not finite (depth_scale {scale})", seq=seq)
    if depth.min() < 0:
        raise ProtocolError("bad_depth", f"negative depth (depth_scale {scale})", seq=seq)
    if depth.max() > LIMITS["max_depth_m"]:
        raise ProtocolError(
            "bad_depth", f"depth up to {depth.max():.0f} m: is depth_scale {scale} right?", seq=seq
        )
    valid = float((depth > 0).mean())
    if valid < LIMITS["min_valid_depth_fraction"]:
        raise ProtocolError(
            "bad_depth",
            f"all-zero depth: {100 * valid:.2f}% of pixels valid, "
            f"need {100 * LIMITS['min_valid_depth_fraction']:.0f}%",
            seq=seq,
        )
    return colour, depth
