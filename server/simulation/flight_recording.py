"""Flight recordings: what one flight of the drone did, kept as plain JSON-able data.

**A flight** opens at the first drone event (``spawned``, say), at an accepted ``takeoff``, or at
the first drone state whose mode is not ``landed`` or ``faulted``, whichever comes first while no
flight is open. It closes at the first state whose mode is ``landed`` or ``faulted`` (that state
is its last: a crash that ends on the ground closes it the same way), when a course result ends
it (:meth:`FlightRecorder.finish`), or when the session ends (:meth:`FlightRecorder.close`).

A recording holds the drone's states as rows of ``STATE_COLUMNS`` (one per published state, at
the session's ``drone_state_hz``), the drone events, the pilot's commands as received (with the
simulation time they arrived at), and, when a course was flown, the course and its result as
the opaque JSON-able dicts the course judge gives. Times are simulation seconds (the
``drone_state.timestamp`` clock, 0 at spawn); positions, velocities and attitudes are in the
session's world frame (metres, m/s, the unit quaternion of T_world_drone's rotation).

Pure data and bookkeeping: no files, no threads of its own (thread-safe: states and events come
from the flight thread, commands from the worker's main thread, snapshots from the mapping
thread); ``on_end`` gets each closed flight, outside the recorder's lock.
"""

from __future__ import annotations

import copy
import io
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from server.geometry import quaternion_from_pose

Json = dict[str, Any]  # a JSON object
FORMAT = "dronesim-flight/1"
# One row per drone state: simulation time (s), position (m, world), velocity (m/s, world),
# attitude (unit quaternion x, y, z, w of T_world_drone, w >= 0), flight mode.
STATE_COLUMNS = ("t", "x", "y", "z", "vx", "vy", "vz", "qx", "qy", "qz", "qw", "mode")
_GROUNDED = ("landed", "faulted")
_DECIMALS = 4  # 0.1 mm, 0.1 mm/s, 1e-4 of a quaternion: far below what the simulator resolves
_MAX_EVENTS = 1000  # per flight; events are rare (collisions repeat at most twice a second)


def _rounded(values: Any) -> list[float]:
    return [round(float(v), _DECIMALS) for v in values]


@dataclass
class FlightRecording:
    """One flight (see the module's docstring); ``as_dict`` is the documented JSON."""

    id: str
    started_at: float  # wall clock when it opened, Unix seconds (the server's clock)
    start_time_s: float  # simulation time of its first entry
    state_hz: float
    end_time_s: float = 0.0  # simulation time of its last entry
    end: str | None = None  # why it closed: landed, faulted, course_finished, session_end
    states: list[list[Any]] = field(default_factory=list)
    events: list[Json] = field(default_factory=list)
    commands: list[Json] = field(default_factory=list)
    course: Json | None = None
    result: Json | None = None
    truncated: bool = False  # the caps were reached: later entries were not kept

    def touch(self, t: float) -> None:
        self.end_time_s = max(self.end_time_s, float(t))

    def as_dict(self) -> dict[str, Any]:
        return {
            "format": FORMAT,
            "id": self.id,
            "started_at": self.started_at,
            "start_time_s": self.start_time_s,
            "end_time_s": self.end_time_s,
            "duration_s": round(self.end_time_s - self.start_time_s, _DECIMALS),
            "finished": self.end is not None and self.end != "in_progress",
            "end": self.end,
            "state_hz": self.state_hz,
            "state_columns": list(STATE_COLUMNS),
            "states": self.states,
            "events": self.events,
            "commands": self.commands,
            "course": self.course,
            "result": self.result,
            "truncated": self.truncated,
        }


def summary(flight: Json) -> dict[str, Any]:
    """What a list of flights shows of one (``as_dict`` -> a few fields)."""
    return {
        "id": flight["id"],
        "started_at": flight["started_at"],
        "duration_s": flight["duration_s"],
        "finished": flight["finished"],
        "end": flight["end"],
        "states": len(flight["states"]),
        "events": len(flight["events"]),
        "commands": len(flight["commands"]),
        "has_course": flight["course"] is not None,
        "result": flight["result"],
    }


def states_csv(flight: Json) -> str:
    """The flight's states as CSV: a header of ``STATE_COLUMNS``, one row per state."""
    out = io.StringIO()
    out.write(",".join(flight["state_columns"]) + "\n")
    for row in flight["states"]:
        out.write(",".join(str(v) for v in row) + "\n")
    return out.getvalue()


def states_tum(flight: Json) -> str:
    """The drone's path as a TUM trajectory: a ``#`` comment, then per state
    ``t x y z qx qy qz qw``: simulation seconds (0 at spawn), the drone's centre in the
    session's world frame (metres) and its attitude (T_world_drone's rotation, unit quaternion,
    w >= 0). The frame is that of the session's trajectory.tum, so evo overlays the two
    (``evo_traj tum flight.tum trajectory.tum``); the clocks differ (trajectory.tum's is the
    client's), so they are not matched by time."""
    columns = list(flight["state_columns"])
    picked = [columns.index(c) for c in ("t", "x", "y", "z", "qx", "qy", "qz", "qw")]
    out = io.StringIO()
    out.write("# timestamp tx ty tz qx qy qz qw (T_world_drone, metres; simulation seconds)\n")
    for row in flight["states"]:
        out.write(" ".join(str(row[i]) for i in picked) + "\n")
    return out.getvalue()


class FlightRecorder:
    """Cuts the drone's life into flights and records each (see the module's docstring).

    max_flight_s: states kept per flight (max_flight_s * state_hz rows; commands up to twice
    that, events up to _MAX_EVENTS); beyond it a flight goes on unrecorded and is marked
    ``truncated``. on_end: called with each closed flight (from the caller's thread, outside
    the lock)."""

    def __init__(
        self,
        state_hz: float,
        max_flight_s: float,
        on_end: Callable[[FlightRecording], None] | None = None,
        first_id: int = 1,
    ) -> None:
        self.state_hz = state_hz
        self.max_states = max(1, int(round(max_flight_s * state_hz)))
        self.on_end = on_end
        self._next_id = first_id
        self._open: FlightRecording | None = None
        self._course: Json | None = None  # the course being flown: goes with each new flight
        self._lock = threading.Lock()

    # ------------------------------------------------------------------ input
    def state(self, t: float, T_world_drone: np.ndarray, velocity: np.ndarray, mode: str) -> None:
        """A drone state: simulation time t (s), its pose (4x4, metres) and velocity (m/s),
        world frame; mode as drone_state.mode."""
        grounded = mode in _GROUNDED
        with self._lock:
            flight = self._open
            if flight is None:
                if grounded:
                    return
                flight = self._start(t)
            row = [
                round(float(t), _DECIMALS),
                *_rounded(T_world_drone[:3, 3]),
                *_rounded(velocity),
                *_rounded(quaternion_from_pose(T_world_drone)),
                mode,
            ]
            if len(flight.states) < self.max_states:
                flight.states.append(row)
            else:
                flight.truncated = True
            flight.touch(t)
            ended = self._end(mode) if grounded else None
        self._tell(ended)

    def event(
        self,
        t: float,
        kind: str,
        position: np.ndarray,
        message: str,
        command_id: int | None,
    ) -> None:
        """A drone event (drone_event's fields; position world frame, metres)."""
        with self._lock:
            flight = self._open or self._start(t)
            if len(flight.events) < _MAX_EVENTS:
                flight.events.append(
                    {
                        "t": round(float(t), _DECIMALS),
                        "event": kind,
                        "position": _rounded(position),
                        "message": message,
                        "command_id": command_id,
                    }
                )
            else:
                flight.truncated = True
            flight.touch(t)

    def command(self, t: float, name: str, command_id: int, fields: dict[str, Any]) -> None:
        """A pilot command the drone accepted, as received (its fields that were given), at
        simulation time t. A takeoff opens a flight; other commands while none is open (sticks
        streamed to a landed drone) are not kept."""
        with self._lock:
            flight = self._open
            if flight is None:
                if name != "takeoff":
                    return
                flight = self._start(t)
            if len(flight.commands) < 2 * self.max_states:
                given = {k: _plain(v) for k, v in fields.items() if v is not None}
                flight.commands.append(
                    {"t": round(float(t), _DECIMALS), "name": name, "id": command_id, **given}
                )
            else:
                flight.truncated = True
            flight.touch(t)

    def set_course(self, course: Json | None) -> None:
        """The course being flown (an opaque JSON-able dict), attached to the open flight and
        to every flight after it until set to None."""
        with self._lock:
            self._course = copy.deepcopy(course)
            if self._open is not None:
                self._open.course = copy.deepcopy(course)

    def finish(self, result: Json) -> FlightRecording | None:
        """The course's result (an opaque JSON-able dict) ends the open flight (end
        ``course_finished``); the drone's next state in the air opens the next one. Returns
        the flight it ended, None when none was open."""
        with self._lock:
            if self._open is None:
                return None
            self._open.result = copy.deepcopy(result)
            ended = self._end("course_finished")
        self._tell(ended)
        return ended

    def close(self, reason: str = "session_end") -> FlightRecording | None:
        """End the open flight (the session ends); returns it, or None."""
        with self._lock:
            ended = self._end(reason) if self._open is not None else None
        self._tell(ended)
        return ended

    # ------------------------------------------------------------------ queries
    def open_flight(self) -> Json | None:
        """A copy of the flight in progress (``end`` ``in_progress``), or None."""
        with self._lock:
            if self._open is None:
                return None
            flight = copy.copy(self._open)
            flight.states = list(flight.states)
            flight.events = list(flight.events)
            flight.commands = list(flight.commands)
            flight.end = "in_progress"
            return flight.as_dict()

    # ------------------------------------------------------------------ inside the lock
    def _start(self, t: float) -> FlightRecording:
        self._open = FlightRecording(
            id=str(self._next_id),
            started_at=time.time(),
            start_time_s=float(t),
            end_time_s=float(t),
            state_hz=self.state_hz,
            course=copy.deepcopy(self._course),
        )
        self._next_id += 1
        return self._open

    def _end(self, reason: str) -> FlightRecording | None:
        flight, self._open = self._open, None
        if flight is not None:
            flight.end = reason
        return flight

    def _tell(self, ended: FlightRecording | None) -> None:
        if ended is not None and self.on_end is not None:
            self.on_end(ended)


def _plain(value: Any) -> Any:
    """A command's field as JSON takes it (numpy arrays and numbers become lists and floats)."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value
