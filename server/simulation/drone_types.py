"""What the drone simulator tells its caller: modes, events, status and the command error.

Everything is in the gravity-aligned flight frame (metres, z up); times are simulation time in
seconds since the drone spawned.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum

import numpy as np
from numpy.typing import ArrayLike

from server.errors import DroneSimError
from server.geometry.arrays import FloatArray
from server.simulation.pilot_modes import FlightMode


class DroneMode(str, Enum):
    """Flight modes, named as in the protocol's drone_state.mode."""

    LANDED = "landed"
    HOVER = "hover"
    MANUAL = "manual"
    GOTO = "goto"
    LANDING = "landing"
    CRASHED = "crashed"  # motors off after a crash, falling until it rests on the map


class DroneEventKind(str, Enum):
    """Kinds of drone_event (shared/protocol.json's enum for its ``event``)."""

    SPAWNED = "spawned"
    COLLISION = "collision"
    ARRIVED = "arrived"
    REPLANNED = "replanned"
    BLOCKED = "blocked"
    LANDED = "landed"
    CRASH = "crash"
    RESTARTED = "restarted"  # put back after a crash in a race (DroneSimulator.put_back)
    # Said by the session around the simulator, never emitted by it: the flight's fault and
    # the running course's judgement (course_judge.GateEvent.kind).
    FAULTED = "faulted"
    GATE_PASSED = "gate_passed"
    GATE_MISSED = "gate_missed"
    COURSE_FINISHED = "course_finished"


class DroneCommandError(DroneSimError):
    """A command cannot be carried out now (no drone yet, wrong mode, bad input): bad_command."""


@dataclass(frozen=True)
class DroneEvent:
    """Something the pilot should hear about (the protocol's drone_event).

    ``message`` names no coordinates itself: where it mentions a point it holds ``{point}``
    and ``point`` is that point (flight frame, m). The simulator cannot say where the point is
    in the pilot's frame; ``text`` writes it in whichever frame the caller maps it to."""

    kind: DroneEventKind
    time_s: float  # simulation time
    position: FloatArray  # (3,) flight frame, m
    message: str
    command_id: int | None = None
    point: np.ndarray | None = None  # (3,) flight frame, m: the ``{point}`` of the message

    def text(self, to_frame: Callable[[FloatArray], ArrayLike] = lambda p: p) -> str:
        """The message with ``{point}`` written as ``(x, y, z) m`` after ``to_frame`` (a map
        from flight-frame points to the reader's frame; identity by default)."""
        if self.point is None:
            return self.message
        x, y, z = np.asarray(to_frame(self.point), dtype=np.float64)
        return self.message.format(point=f"({x:.2f}, {y:.2f}, {z:.2f}) m")


@dataclass(frozen=True)
class DroneStatus:
    """The drone's state for drone_state, in the flight frame (the server maps it to world)."""

    time_s: float  # simulation time since spawn, s
    T_flight_drone: FloatArray  # (4, 4) body to flight frame, m
    velocity: FloatArray  # (3,) flight frame, m/s
    mode: DroneMode
    clearance: float  # distance field at the centre, m
    target: FloatArray | None  # (3,) goto target
    # (N, 3) the remaining route's corners: the setpoint, then the vertices of the path ahead
    # (within route_following.ROUTE_TOLERANCE_M of it when drawn straight), N <=
    # max_route_points; goto only
    route: FloatArray | None
    command_id: int | None
    flight_mode: FlightMode = FlightMode.POSITION  # how sticks fly the drone (pilot_modes.py)
    damage: float = 0.0  # damage points from bumps since spawn
