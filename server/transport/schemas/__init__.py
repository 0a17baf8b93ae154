"""What the REST API returns, as pydantic models: the wire schemas of ``/docs`` (OpenAPI).

The routes return the bodies the sessions assemble (in their worker processes) unchanged; these
models describe them for clients, and the tests check every body against them. Fields are
declared with units and frames. A client must ignore fields it does not know (``extra``
allowed): later versions may add counters. Positions are in the session's world frame (the
camera frame of its first tracked frame, metres; see ``shared/PROTOCOL.md``).

One module per route group (``sessions``, ``status``, ``flights``, ``recordings``,
``viewers``, ``phone``), the base and the error body in ``common``; routes and tests import
every model from here.
"""

from __future__ import annotations

from server.transport.schemas.common import ErrorBody, ErrorDetail, WireModel, error_response
from server.transport.schemas.flights import (
    FlightCommand,
    FlightEvent,
    FlightList,
    FlightRecordingBody,
    FlightSummary,
)
from server.transport.schemas.phone import PhoneLinkBody
from server.transport.schemas.recordings import RecordingCreated, RecordingFrame, RecordingIndex
from server.transport.schemas.rooms import (
    InviteCreated,
    RaceBestEntry,
    RaceFlights,
    RaceList,
    RacePilot,
    RacePilotFlights,
    RaceRecord,
    RaceStart,
    RaceStarted,
    SharedRoom,
)
from server.transport.schemas.sessions import (
    CourseBest,
    CourseResult,
    SessionCreate,
    SessionCreated,
)
from server.transport.schemas.status import (
    DevicePoseUse,
    DroneSummary,
    Failures,
    Intrinsics,
    LoopClosure,
    MapStats,
    SessionStatus,
    TrackingRecovery,
    WorkerInfo,
)
from server.transport.schemas.viewers import ViewerCreated, ViewerList

__all__ = [
    "CourseBest",
    "CourseResult",
    "DevicePoseUse",
    "DroneSummary",
    "ErrorBody",
    "ErrorDetail",
    "Failures",
    "FlightCommand",
    "FlightEvent",
    "FlightList",
    "FlightRecordingBody",
    "FlightSummary",
    "Intrinsics",
    "InviteCreated",
    "LoopClosure",
    "MapStats",
    "PhoneLinkBody",
    "RaceBestEntry",
    "RaceFlights",
    "RaceList",
    "RacePilot",
    "RacePilotFlights",
    "RaceRecord",
    "RaceStart",
    "RaceStarted",
    "RecordingCreated",
    "RecordingFrame",
    "RecordingIndex",
    "SessionCreate",
    "SessionCreated",
    "SessionStatus",
    "SharedRoom",
    "TrackingRecovery",
    "ViewerCreated",
    "ViewerList",
    "WireModel",
    "WorkerInfo",
    "error_response",
]
