"""Validation of messages against protocol.json: field types, ranges and lengths from the
spec, plus what a schema cannot say (plausible image sizes and intrinsics, a command's needed
field, a map chunk's byte lengths, an error's code matching its name)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from server.protocol.errors import ProtocolError
from server.protocol.spec import ERROR_NAMES, LIMITS, MESSAGES, VERSION

_PY_TYPES: dict[str, type | tuple[type, ...]] = {
    "int": int,
    "float": (int, float),
    "str": str,
    "bytes": (bytes, bytearray),
    "bool": bool,
    "list": (list, tuple),
    "map": dict,
}


def _is_kind(value: object, kind: str) -> bool:
    """Whether ``value`` has the protocol type ``kind``; a bool is no number."""
    if isinstance(value, bool):
        return kind == "bool"
    return isinstance(value, _PY_TYPES[kind])


def _check_value(value: Any, spec: Mapping, where: str) -> None:
    kind = spec["type"]
    if not _is_kind(value, kind):
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


_COMMAND_NEEDS = {
    "goto": "target",
    "goto_pixel": "pixel",
    "sticks": "sticks",
    "flight_mode": "flight_mode",
}


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


def _check_map_corrected(msg: Mapping) -> None:
    """Each keyframe: {id, seq (ints >= 0), T_world_keyframe (16 finite floats)}; the schema
    says only that they are maps."""
    for i, kf in enumerate(msg["keyframes"]):
        where = f"map_corrected.keyframes[{i}]"
        if set(kf) != {"id", "seq", "T_world_keyframe"}:
            raise ProtocolError("invalid_field", f"{where} needs id, seq and T_world_keyframe")
        for key in ("id", "seq"):
            _check_value(kf[key], {"type": "int", "min": 0}, f"{where}.{key}")
        _check_value(
            kf["T_world_keyframe"],
            {"type": "list", "length": 16, "items": {"type": "float"}},
            f"{where}.T_world_keyframe",
        )


def _check_error(msg: Mapping) -> None:
    if ERROR_NAMES.get(msg["code"]) != msg["name"]:
        raise ProtocolError("invalid_field", f"error code {msg['code']} is not {msg['name']!r}")


_SEMANTIC_CHECKS = {
    "hello": _check_hello,
    "command": _check_command,
    "map_chunk": _check_map_chunk,
    "map_corrected": _check_map_corrected,
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
    seq = message.get("seq") if type(message.get("seq")) is int else None  # no bool
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
