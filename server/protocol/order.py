"""The order rules of a client's messages (a state machine per connection)."""

from __future__ import annotations

from server.protocol.errors import ProtocolError


class ClientOrder:
    """The order rules of a client's messages by their type: hello first and once, nothing
    after bye. ``check`` raises unexpected_message. A frame's seq is not checked here: the
    session's worker, which decodes the frame, puts frames in order (bad_sequence)."""

    def __init__(self) -> None:
        self.hello = False
        self.closed = False

    def check(self, kind: str) -> None:
        """The client sent a message of type ``kind`` (a client message type)."""
        if self.closed:
            raise ProtocolError("unexpected_message", f"{kind} after bye")
        if kind == "hello":
            if self.hello:
                raise ProtocolError("unexpected_message", "second hello")
            self.hello = True
            return
        if not self.hello:
            raise ProtocolError("unexpected_message", f"{kind} before hello")
        if kind == "bye":
            self.closed = True
