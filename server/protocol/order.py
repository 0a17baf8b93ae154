"""The order rules of a client's messages (a state machine per connection)."""

from __future__ import annotations

from collections.abc import Mapping

from server.protocol.errors import ProtocolError


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
