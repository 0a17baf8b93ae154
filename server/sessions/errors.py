"""Errors of sessions: for their clients, and for the server that saves them."""

from __future__ import annotations

import numpy as np

from server.errors import DroneSimError


class SessionError(DroneSimError):
    """A request a session cannot honour; ``code`` names the reason for the client."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code


class SnapshotError(DroneSimError):
    """A session's map or trajectory could not be written (disk full or gone); the previous
    snapshot on disk is whole and the session still holds everything in memory."""


class CommandRefused(SessionError):
    """A pilot command that cannot be carried out. ``nearest``: a reachable point close to the
    asked target (world frame, metres), when there is one."""

    def __init__(self, code: str, message: str, nearest: np.ndarray | None = None) -> None:
        super().__init__(code, message)
        self.nearest = nearest
