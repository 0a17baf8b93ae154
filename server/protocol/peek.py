"""A cheap look at a client message before (or instead of) decoding it: its ``type`` and, for a
frame, its ``seq``, read from the top-level msgpack map without unpacking the other values.

The web process routes every client message by its type, and forwards a frame to the session's
worker as the bytes that arrived: the worker decodes and validates it once (``decode``). Only
the type (the client's message order) and the seq (to name the frame in an error the web
process answers itself) are read here. Other values are skipped in place (``Unpacker.skip``,
which builds nothing), so a frame's images cost nothing.
"""

from __future__ import annotations

from typing import NamedTuple

import msgpack

from server.protocol.errors import ProtocolError, check_raw

# Fields read one by one at most; a map with more entries (no message of this version has
# that many) is unpacked whole, in C, as ``decode`` would, so that a message of many tiny
# entries never costs a Python loop per entry.
MAX_PEEKED_FIELDS = 64


class Peek(NamedTuple):
    """What ``peek`` read: the message's type, and its seq when that is an int (None else)."""

    kind: str
    seq: int | None


def peek(data: object, *, max_bytes: int | None = None) -> Peek:
    """The ``type`` and ``seq`` of one message, the size checked first as ``decode`` does.
    Raises ProtocolError: ``message_too_big``; ``malformed_message`` when ``data`` is not
    bytes, not one msgpack map (garbage, cut short, trailing bytes), or has no str ``type``.
    Whatever else ``decode`` would refuse (unknown types, fields) is not checked here."""
    raw = check_raw(data, max_bytes)
    try:
        kind, seq = _read(memoryview(raw).cast("B"))
    except (ValueError, TypeError, OverflowError, msgpack.UnpackException) as exc:
        raise ProtocolError("malformed_message", f"not one msgpack map: {exc}") from exc
    if not isinstance(kind, str):
        raise ProtocolError("malformed_message", "a message is a map with a str 'type' field")
    return Peek(kind, seq)


def _read(view: memoryview) -> tuple[object, int | None]:
    unpacker = msgpack.Unpacker(raw=False, max_buffer_size=max(len(view), 1))
    unpacker.feed(view)
    entries = unpacker.read_map_header()  # ValueError when it is no map
    if entries > MAX_PEEKED_FIELDS:
        return _whole(view)
    kind: object = None
    seq: int | None = None
    for _ in range(entries):
        if not _is_str(view, unpacker.tell()):  # no field's key (decode may refuse it)
            unpacker.skip()
            unpacker.skip()
            continue
        key = unpacker.unpack()
        wanted = _READ.get(key)
        value = None  # a type that is no str, a seq that is no int: read as none
        if wanted is not None and wanted(view, unpacker.tell()):
            value = unpacker.unpack()
        else:
            unpacker.skip()
        # As in a dict, a repeated key's last value is the one that counts.
        if key == "type":
            kind = value
        elif key == "seq":
            seq = value
    if unpacker.tell() != len(view):
        raise ValueError("trailing bytes after the message")
    return kind, seq


def _whole(view: memoryview) -> tuple[object, int | None]:
    message = msgpack.unpackb(view, raw=False, strict_map_key=False)
    if not isinstance(message, dict):
        raise ValueError("not a map")
    seq = message.get("seq")
    return message.get("type"), seq if type(seq) is int else None


def _header(view: memoryview, at: int) -> int:
    if at >= len(view):
        raise msgpack.OutOfData("the message is cut short")
    return view[at]


def _is_str(view: memoryview, at: int) -> bool:
    """Whether the value at ``at`` is a msgpack str (fixstr, str 8/16/32)."""
    header = _header(view, at)
    return 0xA0 <= header <= 0xBF or header in (0xD9, 0xDA, 0xDB)


def _is_int(view: memoryview, at: int) -> bool:
    """Whether the value at ``at`` is a msgpack int (fixints, uint and int 8-64; no bool)."""
    header = _header(view, at)
    return header <= 0x7F or header >= 0xE0 or 0xCC <= header <= 0xD3


# The fields read, and the kind of value each is read as.
_READ = {"type": _is_str, "seq": _is_int}
