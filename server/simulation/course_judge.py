"""The judge of a course: gates passed, missed or flown the wrong way, timed and scored.

Everything is in the flight frame (metres, z up, seconds of simulation time).

The drone passes a gate when the segment between two consecutive positions it is judged at
crosses the ring's plane from the back (``(p - centre) . normal < 0``) to the front (``>= 0``)
at a point within the radius of the centre (the drone's centre, not its whole sphere); crossing
from the front is the wrong way and counts for nothing (``wrong_way``). Gates are taken in
order: only the next gate and the one after it are judged, and passing the one after marks the
next one missed. The run finishes when every gate is passed or missed.

**Score** (``CourseRun.score``, an integer, never below 0)::

    100 per gate passed - 50 per gate missed - 10 per bump - 100 per crash
    + time bonus (finished runs only): 50 per gate x clamp((2 par - time) / par, 0, 1)

``par`` is the duration of the course's own route at the speed it was planned for (the
autopilot's time), ``time`` the run's time from the start to its last gate: at par or faster the
full bonus, none at twice par. A clean autopilot run scores about 150 per gate.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

import numpy as np
from numpy.typing import ArrayLike

from server.geometry.arrays import FloatArray
from server.simulation.course import Course, Gate

# Score (module docstring).
POINTS_PASSED = 100
POINTS_MISSED = -50
POINTS_BUMP = -10
POINTS_CRASH = -100
TIME_BONUS_PER_GATE = 50
RESTART_PAST_M = 0.3  # a restart puts the drone this far past the last gate passed


class GateState(str, Enum):
    PENDING = "pending"
    PASSED = "passed"
    MISSED = "missed"


@dataclass(frozen=True)
class GateEvent:
    """``kind``: gate_passed, gate_missed or course_finished; ``gate``: its index (the last
    gate's for course_finished); ``point``: where the drone crossed (or was), flight frame."""

    kind: str
    gate: int
    time_s: float
    point: FloatArray


def crossing(gate: Gate, p0: FloatArray, p1: FloatArray) -> tuple[float, bool, bool] | None:
    """Where the segment p0 -> p1 crosses the gate's plane: (fraction along it, forward,
    inside the ring), or None when it does not cross. Forward: from the back to the front."""
    s0 = float((p0 - gate.centre) @ gate.normal)
    s1 = float((p1 - gate.centre) @ gate.normal)
    forward = s0 < 0.0 <= s1
    backward = s1 < 0.0 <= s0
    if not (forward or backward) or s0 == s1:
        return None
    t = s0 / (s0 - s1)
    point = p0 + t * (p1 - p0)
    return t, forward, bool(np.linalg.norm(point - gate.centre) <= gate.radius_m)


class CourseRun:
    """A flight through a course, judged from the drone's positions: ``update(time, position)``
    at every step or tick (the segment from the last position to this one is judged),
    ``collision(crash)`` for each bump or crash. Not thread-safe: one caller."""

    def __init__(self, course: Course, start_time_s: float, position: ArrayLike) -> None:
        self.course = course
        self.start_time_s = float(start_time_s)
        self.states = [GateState.PENDING] * len(course.gates)
        self.next_gate = 0
        self.bumps = 0
        self.crashes = 0
        self.wrong_way = 0  # crossings of the next gate's ring from the front
        self.restarts = 0  # times the drone was put back after a crash (``restarted``)
        self.finished_at_s: float | None = None
        self.start_position = np.asarray(position, dtype=float).reshape(3).copy()
        self._last = self.start_position.copy()
        self._last_time = self.start_time_s
        self._time = self.start_time_s

    @property
    def finished(self) -> bool:
        return self.finished_at_s is not None

    def move_with_world(self, T: FloatArray) -> None:
        """The world moved under the run (loop closure; ``T`` 4x4, flight frame, metres, as the
        drone was moved): the gates and the last judged position move with it, so that the
        drone's jump is not judged as a flight through a ring."""
        self.course = self.course.moved(T)
        T = np.asarray(T, dtype=float)
        self._last = T[:3, :3] @ self._last + T[:3, 3]
        self.start_position = T[:3, :3] @ self.start_position + T[:3, 3]

    @property
    def last_passed(self) -> int | None:
        """The index of the last gate passed (gates are passed in order), or None."""
        passed = [i for i, state in enumerate(self.states) if state == GateState.PASSED]
        return passed[-1] if passed else None

    def restart_pose(self, past_m: float = RESTART_PAST_M) -> tuple[FloatArray, FloatArray]:
        """Where a crashed drone restarts: (point, unit heading), ``past_m`` beyond the last gate
        passed along its normal, or the start, heading for the first gate, before any."""
        if self.last_passed is not None:
            gate = self.course.gates[self.last_passed]
            return gate.centre + past_m * gate.normal, gate.normal.copy()
        way = self.course.gates[0].centre - self.start_position
        norm = float(np.linalg.norm(way))
        heading = way / norm if norm > 1e-9 else self.course.gates[0].normal
        return self.start_position.copy(), heading

    def restarted(self, time_s: float, position: ArrayLike) -> None:
        """The drone was put back at ``position`` (``restart_pose``): the jump there is not
        judged as a flight through a ring; the clock runs on."""
        self._last = np.asarray(position, dtype=float).reshape(3).copy()
        self._last_time = self._time = float(time_s)
        self.restarts += 1

    @property
    def passed(self) -> int:
        return sum(s == GateState.PASSED for s in self.states)

    @property
    def missed(self) -> int:
        return sum(s == GateState.MISSED for s in self.states)

    def elapsed_s(self) -> float:
        """From the start to the finish, or to the latest update while running."""
        end = self.finished_at_s if self.finished_at_s is not None else self._time
        return end - self.start_time_s

    def update(self, time_s: float, position: ArrayLike) -> list[GateEvent]:
        """The drone is at ``position`` at ``time_s``: judge the segment from the last one."""
        p1 = np.asarray(position, dtype=float).reshape(3)
        p0, t0 = self._last, self._last_time
        self._last, self._last_time, self._time = p1.copy(), float(time_s), float(time_s)
        if self.finished:
            return []
        gates = self.course.gates
        events: list[GateEvent] = []
        done = -1.0  # along the segment: crossings up to here are judged
        while not self.finished:
            first = None  # the earliest crossing inside a judged ring after ``done``
            for j in (self.next_gate, self.next_gate + 1):
                hit = crossing(gates[j], p0, p1) if j < len(gates) else None
                if hit is not None and hit[0] > done and hit[2]:
                    if first is None or hit[0] < first[0]:
                        first = (hit[0], j, hit[1])
            if first is None:
                break
            t, j, forward = first
            done = t
            if not forward:
                self.wrong_way += j == self.next_gate
                continue
            at = t0 + t * (time_s - t0)
            point = p0 + t * (p1 - p0)
            if j == self.next_gate + 1:  # the next one was left out
                self.states[self.next_gate] = GateState.MISSED
                events.append(GateEvent("gate_missed", self.next_gate, at, point))
            self.states[j] = GateState.PASSED
            events.append(GateEvent("gate_passed", j, at, point))
            self.next_gate = j + 1
            if self.next_gate == len(gates):
                self.finished_at_s = at
                events.append(GateEvent("course_finished", j, at, point))
        return events

    def collision(self, crash: bool) -> None:
        """A bump (or a crash) while the run goes on."""
        if self.finished:
            return
        if crash:
            self.crashes += 1
        else:
            self.bumps += 1

    def score(self) -> int:
        """Module docstring: gates, penalties, and the time bonus once finished."""
        n = len(self.course.gates)
        points: float = (
            POINTS_PASSED * self.passed
            + POINTS_MISSED * self.missed
            + POINTS_BUMP * self.bumps
            + POINTS_CRASH * self.crashes
        )
        if self.finished:
            par = max(self.course.par_s, 1e-3)
            share = min(1.0, max(0.0, (2 * par - self.elapsed_s()) / par))
            points += TIME_BONUS_PER_GATE * n * share
        return max(0, int(round(points)))


def judge_path(course: Course, path: FloatArray, times: FloatArray | None = None) -> CourseRun:
    """A run judged along a path (N, 3), each point one update at ``times`` (N,) s (None:
    1 s apart): the generator's check that a route flies the course."""
    stamps = np.arange(len(path), dtype=float) if times is None else np.asarray(times, float)
    run = CourseRun(course, float(stamps[0]), path[0])
    for t, p in zip(stamps[1:], path[1:], strict=True):
        run.update(float(t), p)
        if run.finished:
            break
    return run
