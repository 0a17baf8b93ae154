"""Protocol errors: the exception every check raises and the ``error`` message it becomes."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from server.errors import DroneSimError
from server.protocol.spec import ERROR_NAMES, ERRORS, LIMITS, MAX_SEQ


class ProtocolError(DroneSimError):
    """A message breaks the protocol. ``code`` is an error name from protocol.json."""

    def __init__(
        self,
        code: str,
        message: str,
        *,
        seq: int | None = None,
        command_id: int | None = None,
        counted: bool = True,
    ) -> None:
        if code not in ERRORS:
            raise ValueError(f"unknown protocol error code {code!r}; known: {sorted(ERRORS)}")
        super().__init__(f"{code}: {message}")
        self.code, self.message, self.seq = code, message, seq
        self.command_id = command_id  # the refused command's id, when it could be read
        # Whether it counts toward max_consecutive_errors: an empty depth map does not (a
        # phone's depth from motion starts empty and may stay so for seconds).
        self.counted = counted

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
        """The error for the client; a seq or command id that is itself invalid (e.g.
        negative) is left out, as the error message could not carry it."""
        valid = isinstance(self.seq, int) and 0 <= self.seq <= MAX_SEQ
        command_id = self.command_id
        if not (isinstance(command_id, int) and 0 <= command_id <= MAX_SEQ):
            command_id = None
        return make_error(
            self.code, self.message, seq=self.seq if valid else None, command_id=command_id
        )


def check_raw(data: object, max_bytes: int | None = None) -> bytes | bytearray | memoryview:
    """``data`` itself, once it is what any message must be before it is read: bytes (a text
    frame is not), at most ``max_bytes`` long (the protocol's limit when None). Raises
    ProtocolError (malformed_message, message_too_big)."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise ProtocolError("malformed_message", f"need binary data, got {type(data).__name__}")
    limit = LIMITS["max_message_bytes"] if max_bytes is None else max_bytes
    if len(data) > limit:
        raise ProtocolError("message_too_big", f"{len(data)} bytes, limit {limit}")
    return data


def new_message(kind: str, **fields: Any) -> dict:
    """A message of type ``kind``; fields that are None are left out (optional fields)."""
    return {"type": kind, **{k: v for k, v in fields.items() if v is not None}}


def floats(values: ArrayLike, n: int, name: str) -> list[float]:
    """``values`` flattened to n floats for the field ``name``; raises invalid_field."""
    flat = np.asarray(values, dtype=np.float64).reshape(-1)
    if flat.size != n:
        raise ProtocolError("invalid_field", f"{name} needs {n} numbers, got {flat.size}")
    return flat.tolist()


def make_error(
    code: str | int,
    message: str,
    *,
    seq: int | None = None,
    command_id: int | None = None,
    nearest: ArrayLike | None = None,
) -> dict:
    """code: an error name ('corrupt_image') or its number (200); nearest: world metres."""
    name = ERROR_NAMES.get(code, code) if isinstance(code, int) else code
    if name not in ERRORS:
        raise ValueError(f"unknown protocol error code {code!r}")
    entry = ERRORS[name]
    return new_message(
        "error",
        code=entry["code"],
        name=name,
        message=message[:1024],
        fatal=entry["fatal"],
        seq=seq,
        command_id=command_id,
        nearest=None if nearest is None else floats(nearest, 3, "nearest"),
    )
