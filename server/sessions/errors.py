"""Errors a session raises for its client."""

from __future__ import annotations

from server.errors import DroneSimError


class SessionError(DroneSimError):
    """A request a session cannot honour; ``code`` names the reason for the client."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code
