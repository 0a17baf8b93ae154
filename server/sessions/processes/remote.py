"""Errors across a process boundary: an exception raised in a session's worker (or its mapper, or
a Ray actor) crosses as a :class:`RemoteError`, plain values that pickle whatever the exception
class looks like, and is raised again on the other side by :func:`raise_remote` as the class the
web side answers for (SessionError, CommandRefused, ProtocolError, SnapshotError, MapError,
OSError; anything else as the session's internal failure).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from server import protocol as proto
from server.mapping.tsdf import MapError
from server.sessions.errors import CommandRefused, SessionError, SnapshotError


@dataclass
class RemoteError:
    """An exception raised in the worker, as plain values (``kind`` names its class)."""

    kind: str
    code: str
    message: str
    nearest: list[float] | None = None


def as_remote(exc: BaseException) -> RemoteError:
    if isinstance(exc, CommandRefused):
        nearest = None if exc.nearest is None else [float(v) for v in exc.nearest]
        return RemoteError("command", exc.code, str(exc), nearest)
    if isinstance(exc, SessionError):
        return RemoteError("session", exc.code, str(exc))
    if isinstance(exc, proto.ProtocolError):
        return RemoteError("protocol", exc.code, str(exc))
    if isinstance(exc, SnapshotError):
        return RemoteError("snapshot", "snapshot_failed", str(exc))
    if isinstance(exc, MapError):
        return RemoteError("map", "map_unavailable", str(exc))
    if isinstance(exc, OSError):  # a disk that refuses a snapshot: the caller keeps its data
        return RemoteError("os", type(exc).__name__, str(exc))
    return RemoteError("internal", "internal_error", f"{type(exc).__name__}: {exc}")


def raise_remote(error: RemoteError) -> None:
    """Raise, on the web side, the exception a worker's call raised."""
    if error.kind == "command":
        nearest = None if error.nearest is None else np.asarray(error.nearest)
        raise CommandRefused(error.code, error.message, nearest)
    if error.kind == "session":
        raise SessionError(error.code, error.message)
    if error.kind == "protocol":
        raise proto.ProtocolError(error.code, error.message)
    if error.kind == "snapshot":
        raise SnapshotError(error.message)
    if error.kind == "map":
        raise MapError(error.message)
    if error.kind == "os":
        raise OSError(f"{error.code}: {error.message}")
    raise RuntimeError(f"the session's worker failed: {error.message}")
