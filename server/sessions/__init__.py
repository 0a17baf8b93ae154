"""Live sessions: one phone (or replaying client) streaming frames into its own tracker and map.

No web code here: the transport hands decoded frames and commands in and gets updates back.
"""

from server.sessions.errors import CommandRefused, SessionError
from server.sessions.live import LiveSession, SessionTakenOver
from server.sessions.manager import SessionManager
from server.sessions.session import Session
from server.sessions.updates import (
    DroneNotice,
    DroneUpdate,
    FrameData,
    FrameRefused,
    MapCorrected,
    MapUpdate,
    PoseUpdate,
    SessionFailed,
)

__all__ = [
    "CommandRefused",
    "DroneNotice",
    "DroneUpdate",
    "FrameData",
    "FrameRefused",
    "LiveSession",
    "MapCorrected",
    "MapUpdate",
    "PoseUpdate",
    "Session",
    "SessionError",
    "SessionFailed",
    "SessionTakenOver",
    "SessionManager",
]
