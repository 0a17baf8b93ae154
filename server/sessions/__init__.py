"""Live sessions: one phone (or replaying client) streaming frames into its own tracker and map.

No web code here: the transport hands decoded frames in and gets pose updates back.
"""

from server.sessions.manager import SessionManager
from server.sessions.session import FrameData, MapUpdate, PoseUpdate, Session, SessionError

__all__ = ["FrameData", "MapUpdate", "PoseUpdate", "Session", "SessionError", "SessionManager"]
