"""``peek``: a client message's type and seq, read without unpacking the rest (the web process
routes by it and forwards a frame unread; server/protocol/peek.py)."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest

from server import protocol as P
from server.protocol import ProtocolError
from server.protocol.peek import MAX_PEEKED_FIELDS


def expect(code: str, data, **kwargs) -> ProtocolError:
    with pytest.raises(ProtocolError) as info:
        P.peek(data, **kwargs)
    assert info.value.code == code, str(info.value)
    return info.value


def frame_bytes(seq: int = 7) -> bytes:
    colour = np.full((480, 640, 3), 128, np.uint8)
    return P.encode(P.make_frame(seq, 1.5, colour, np.ones((480, 640))))


def test_a_frame_s_type_and_seq_are_read_and_its_images_are_not_unpacked(monkeypatch):
    data = frame_bytes(41)
    built = []

    class Unpacker(msgpack.Unpacker):
        def unpack(self):
            value = super().unpack()
            built.append(value)
            return value

    monkeypatch.setattr(msgpack, "Unpacker", Unpacker)
    assert P.peek(data) == P.Peek("frame", 41)
    # Only the keys, the type and the seq were built: the JPEG and PNG were skipped.
    assert sorted(map(str, built)) == sorted(map(str, [*P.decode(data), "frame", 41]))


@pytest.mark.parametrize(
    "message",
    [
        P.make_hello("t", [525.0, 525.0, 319.5, 239.5], (640, 480)),
        P.make_bye(),
        P.make_command(3, "takeoff"),
        P.make_command(4, "goto_pixel", pixel=[1.0, 2.0], seq=9),
    ],
    ids=["hello", "bye", "command", "command with a seq"],
)
def test_other_messages_give_their_type(message):
    peeked = P.peek(P.encode(message))
    assert peeked.kind == message["type"]
    assert peeked.seq == message.get("seq")


def test_keys_anywhere_and_repeated_keys_read_as_a_dict_would():
    data = msgpack.packb({"colour": b"x" * 1000, "seq": 5, "depth": [1, 2], "type": "frame"})
    assert P.peek(data) == ("frame", 5)
    # A key twice: the last value counts, as when the message is unpacked into a dict.
    twice = b"\x83" + b"".join(
        msgpack.packb(v) for v in ("type", "hello", "seq", 1, "type", "frame")
    )
    assert P.peek(twice) == ("frame", 1)
    assert msgpack.unpackb(twice) == {"type": "frame", "seq": 1}


def test_a_long_encoding_of_a_short_key_is_still_the_key():
    """str 8 for "type" (an encoder may use it): the same key as a fixstr."""
    data = b"\x82" + b"\xd9\x04type" + msgpack.packb("frame") + msgpack.packb("seq") + b"\x07"
    assert P.peek(data) == ("frame", 7)


@pytest.mark.parametrize(
    "seq, read",
    [(0, 0), (127, 127), (2**53 - 1, 2**53 - 1), (-1, -1), ("7", None), (True, None), (1.0, None)],
)
def test_a_seq_is_read_only_when_it_is_an_int(seq, read):
    """Bools and floats are not ints here (nor in the protocol); an out-of-range int is read
    (decode refuses it later, and an error message leaves it out)."""
    assert P.peek(msgpack.packb({"type": "frame", "seq": seq})).seq == read


@pytest.mark.parametrize(
    "data",
    [
        b"",
        b"\xc1",  # a byte msgpack never uses
        b"\x93\x01\x02\x03",  # an array
        msgpack.packb("frame"),
        msgpack.packb({"seq": 1}),  # no type
        msgpack.packb({"type": 5, "seq": 1}),  # a type that is no str
        msgpack.packb({"type": b"frame"}),  # bytes, not str
        msgpack.packb({"type": ["frame"]}),
        msgpack.packb({"type": "frame"}) + b"\x00",  # trailing bytes
        b"\x82\xa4type\xa5frame",  # a map of two entries with one
        b"\x81\xa4type\xa5fra",  # cut inside a value
        b"\x81\xa4ty",  # cut inside a key
        b"\x81\xa4type\xc4\xff\x00",  # a value longer than the message
        b"\xdf\xff\xff\xff\xff",  # a map header claiming 4 billion entries, and nothing else
        b"\x81\xa4type\xa2\xff\xfe",  # a str that is no UTF-8
        "a text frame",
        None,
    ],
)
def test_garbage_is_a_malformed_message(data):
    expect("malformed_message", data)


@pytest.mark.parametrize("cut", [1, 10, 100, 1000, -1])
def test_a_frame_cut_short_is_malformed(cut):
    expect("malformed_message", frame_bytes()[:cut])


def test_deep_nesting_is_refused_not_a_crash():
    data = b"\x82\xa4type\xa5frame\xa1x" + b"\x91" * 100_000 + b"\xc0"
    expect("malformed_message", data)


def test_the_size_is_checked_before_anything_is_read(monkeypatch):
    def must_not_run(*args, **kwargs):
        raise AssertionError("read an oversized message")

    monkeypatch.setattr(msgpack, "Unpacker", must_not_run)
    error = expect("message_too_big", bytes(P.LIMITS["max_message_bytes"] + 1))
    assert error.close_code == P.CLOSE_CODES["message_too_big"]
    expect("message_too_big", bytes(2000), max_bytes=1024)
    data = frame_bytes()
    expect("message_too_big", data, max_bytes=len(data) - 1)


def test_a_map_of_many_entries_is_read_whole_not_entry_by_entry():
    many = {f"k{i}": i for i in range(MAX_PEEKED_FIELDS + 1)} | {"type": "frame", "seq": 3}
    assert P.peek(msgpack.packb(many)) == ("frame", 3)
    assert P.peek(msgpack.packb(many | {"seq": "3"})) == ("frame", None)
    expect("malformed_message", msgpack.packb(many | {"type": 1}))
    expect("malformed_message", msgpack.packb(many) + b"\x00")


def test_peek_agrees_with_decode_on_the_type_of_every_valid_message():
    messages = [
        P.make_hello("t", [525.0, 525.0, 319.5, 239.5], (640, 480)),
        P.make_bye(),
        P.make_command(1, "hold"),
    ]
    for data in [P.encode(m) for m in messages] + [frame_bytes()]:
        decoded = P.decode(data)
        assert P.peek(data) == (decoded["type"], decoded.get("seq"))
