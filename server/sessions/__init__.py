"""Live sessions: one phone (or replaying client) streaming frames into its own tracker and map.

No web code here: the transport hands decoded frames and commands in and gets updates back.
A session spans processes, and the folders say which one a module runs in: ``web/`` in the web
process, ``runtime/`` in the session's worker process, ``processes/`` how those processes (and
the mapper and loop processes, or Ray actors) start and talk. What every side shares is here at
the top: the updates that cross between them, ``SessionConfig``, the store and the flight
recordings on disk, and the errors and failure counting.
"""

from server.sessions.errors import CommandRefused, SessionError
from server.sessions.runtime.session import Session
from server.sessions.updates import (
    DroneNotice,
    DroneUpdate,
    FrameData,
    FrameRefused,
    MapCorrected,
    MapUpdate,
    PoseUpdate,
    RoomUpdate,
    SessionFailed,
)
from server.sessions.web.live import LiveSession, SessionTakenOver
from server.sessions.web.manager import SessionManager

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
    "RoomUpdate",
    "Session",
    "SessionError",
    "SessionFailed",
    "SessionTakenOver",
    "SessionManager",
]
