"""What a flight's recording is given: the pilot's commands, each flight step's events and state,
and the course being flown (server/simulation/flight_recording.py records, sessions/flight_store.py
saves).

A recording that fails must not stop the drone or the course: each failure goes to
``on_failure`` (the flight counts and logs it, from the ``except`` block) and the flight goes on.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from server.sessions.updates import DroneNotice, DroneUpdate
from server.simulation.flight_recording import FlightRecorder

# What a flight recording keeps of a course message (PROTOCOL.md, "Flight recordings").
_COURSE_FIELDS = ("course_id", "difficulty", "seed", "gates", "par_s", "autopilot")
_RESULT_FIELDS = ("course_id", "elapsed_s", "par_s", "score", "bumps", "crashes", "rank")


class FlightRecords:
    """Feeds one session's FlightRecorder, if it has one (``recorder``, set by the session)."""

    def __init__(self, on_failure: Callable[[str], None]) -> None:
        self.recorder: FlightRecorder | None = None
        self._on_failure = on_failure
        self._course: int | None = None  # course_id attached to the recording

    def command(self, now_s: float, name: str, command_id: int, fields: dict[str, Any]) -> None:
        """A command that was carried out at ``now_s`` (simulation time)."""
        if self.recorder is None:
            return
        try:
            self.recorder.command(now_s, name, command_id, fields)
        except Exception:  # the command was carried out; only its record is missing
            self._on_failure("recording a command")

    def course(self, message: dict) -> None:
        """Attach a ``course`` message's course to the flight being recorded; a finished
        course's result (score, time, gates, bumps, crashes, rank) ends that flight, a stopped
        one is detached."""
        recorder = self.recorder
        if recorder is None:
            return
        try:
            state = message["state"]
            if state == "running" and message["course_id"] != self._course:
                recorder.set_course({k: message[k] for k in _COURSE_FIELDS})
                self._course = message["course_id"]
            elif state == "finished" and message["course_id"] == self._course:
                result = {k: message[k] for k in _RESULT_FIELDS}
                result["gates_passed"] = message["gate_states"].count("passed")
                result["gates_missed"] = message["gate_states"].count("missed")
                recorder.finish(result)
                recorder.set_course(None)
                self._course = None
            elif state == "stopped" and self._course is not None:
                recorder.set_course(None)
                self._course = None
        except Exception:  # a recording that fails must not stop the course: counted, logged
            self._on_failure("recording a course")

    def step(self, notices: list[DroneNotice | dict], state: DroneUpdate | None) -> None:
        """A flight step's events, course messages and state."""
        if self.recorder is None:
            return
        try:
            for n in notices:
                if isinstance(n, dict):
                    if n.get("type") == "course":
                        self.course(n)
                    continue
                self.recorder.event(n.timestamp, n.event.value, n.position, n.message, n.command_id)
            if state is not None:
                self.recorder.state(
                    state.timestamp, state.T_world_drone, state.velocity, state.mode
                )
        except Exception:  # a recording that fails must not stop the drone: counted, logged
            self._on_failure("recording a flight step")
