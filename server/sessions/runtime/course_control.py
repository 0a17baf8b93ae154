"""The session's course: ``course_start`` lays one in the drone's map (server.simulation.course),
each flight step judges the drone's way through it, an autopilot may fly it, and finished runs
go into the session's best list (``course_best.json`` beside its other files).

``Flight`` owns one ``CourseControl`` and is its ``CourseFlight``, the little a course needs of a
flight: ``command`` comes from the worker's main thread (like a goto), ``tick`` from the flight
thread after each physics advance, both around ``CourseFlight.lock``, the one lock over the
simulator. What it hands out goes through ``CourseFlight.publish``: ``DroneNotice`` for
gate_passed, gate_missed and course_finished, and ready ``course`` protocol messages (dicts,
sent as they are).

The course is laid on a copy of the flight map taken under the lock and generated outside it
(up to a few hundred milliseconds; the flight thread flies on meanwhile). With ``autopilot`` the
drone first stops where it is and the course starts there; the route it then flies is planned
anew through the gates left (``plan_course_route``) when the map changes under it.
"""

from __future__ import annotations

import copy
import json
import logging
import secrets
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from server import protocol as proto
from server.atomic import atomic_write_bytes
from server.sessions.errors import CommandRefused
from server.sessions.updates import DroneNotice
from server.simulation.config import SimulationConfig
from server.simulation.course import Course, CourseError, course_spec, plan_course_route
from server.simulation.course_generation import course_through, generate_course
from server.simulation.course_judge import CourseRun, GateEvent
from server.simulation.drone import DroneSimulator
from server.simulation.drone_types import DroneCommandError, DroneEvent, DroneEventKind, DroneMode
from server.simulation.flight_map import FlightMap
from server.simulation.route import PlanningError, Reason

log = logging.getLogger(__name__)


class CourseFlight(Protocol):
    """What a course needs of the flight it runs in (``server.sessions.runtime.flight.Flight``): the
    simulator and its map (used under ``lock``), the flight's settings and log, its frames
    (``to_world``: flight-frame points (3,) or (N, 3) in the client's world, metres;
    ``direction_to_world``: directions the same way), and its way out (``publish`` sends a
    ``DroneNotice`` or a protocol message; ``record_course`` keeps a course message in the
    flight's recording)."""

    sim: DroneSimulator
    flight_map: FlightMap
    config: SimulationConfig
    log: logging.Logger | logging.LoggerAdapter

    @property
    def lock(self) -> Any: ...  # a threading.Lock: the one the simulator and its map are used under

    def to_world(self, p_flight: np.ndarray) -> np.ndarray: ...

    def direction_to_world(self, v_flight: np.ndarray) -> np.ndarray: ...

    def publish(self, update: Any) -> None: ...

    def record_course(self, message: dict) -> None: ...


COURSE_COMMANDS = frozenset({"course_start", "course_stop"})
BEST_FILE = "course_best.json"  # in the session's folder (SessionStore.file)
BEST_KEPT = 10  # finished runs kept in the best list
STATE_PERIOD_S = 0.5  # a running course's message at least this often (simulation time)
AUTOPILOT_RETRIES = 3  # an interrupted autopilot route is planned anew this often a course
RESTART_AFTER_S = 1.0  # restart_after_crash: put back this long after a crash (simulation time)
_FLYING = (DroneMode.HOVER, DroneMode.MANUAL, DroneMode.GOTO)


@dataclass(frozen=True)
class CourseResult:
    """One finished run, as the best list keeps it (``GET .../course/best``)."""

    score: int
    time_s: float
    par_s: float
    gates: int
    passed: int
    missed: int
    bumps: int
    crashes: int
    difficulty: str
    seed: int
    autopilot: bool
    finished_at: float  # Unix seconds, the server's clock


def read_best(path: Path | None) -> list[dict[str, Any]]:
    """The best list in ``path``, best first; [] when there is none (or it is unreadable)."""
    return [] if path is None else read_records(path, "results", "the course best list")


def read_records(path: Path, key: str, what: str) -> list[dict[str, Any]]:
    """The JSON objects listed under ``key`` in the file ``path`` (a best list, a session's
    races); [] when there is none, or it is unreadable (logged, naming ``what``: it starts
    anew)."""
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        return []
    except (OSError, ValueError) as exc:
        log.warning("%s %s is unreadable (%s); starting a new one", what, path, exc)
        return []
    records = data.get(key) if isinstance(data, dict) else None
    return [r for r in records if isinstance(r, dict)] if isinstance(records, list) else []


def write_records(path: Path, key: str, records: list[dict[str, Any]]) -> None:
    """``records`` listed under ``key`` in the file ``path``, written atomically (what
    ``read_records`` reads). Raises OSError."""
    atomic_write_bytes(path, json.dumps({key: records}, indent=1).encode())


def _ranked(results: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Highest score first; equal scores: the faster, then the earlier."""
    return sorted(results, key=lambda r: (-r["score"], r["time_s"], r["finished_at"]))


class CourseControl:
    """The course of one session's drone (module docstring)."""

    def __init__(self, flight: CourseFlight, best_path: Path | None = None) -> None:
        self.flight = flight
        self.best_path = best_path  # None: the best list lives in memory only
        self._best: list[dict[str, Any]] | None = None  # read from best_path on first use
        self.run: CourseRun | None = None
        self.state = "stopped"
        self.autopilot = False
        self.course_id = 0
        self.command_id: int | None = None
        self.rank: int | None = None
        self._sent_at = -np.inf  # simulation time of the last course message
        self._speed: float | None = None
        self._retries = 0  # autopilot routes resumed in this course
        self.restart_after_crash = False  # put a crashed drone back at the last gate passed
        self._crashed_at: float | None = None  # simulation time of a crash not restarted yet

    # ------------------------------------------------------------------ commands
    def plan(self, difficulty: str, seed: int | None) -> Course:
        """A course laid from where the drone is, not started: a shared room's race, whose
        gates every drone of the room then flies (``command`` with ``through``). Raises
        CommandRefused."""
        try:
            spec = course_spec(difficulty or "medium")
        except CourseError as exc:
            raise CommandRefused("bad_command", str(exc)) from None
        sim = self.flight.sim
        with self.flight.lock:
            if not sim.spawned:
                raise CommandRefused("bad_command", "no drone yet: it spawns with the first map")
            start = sim.status().T_flight_drone[:3, 3]
            snapshot = copy.deepcopy(self.flight.flight_map)
        seed = secrets.randbelow(2**31) if seed is None else int(seed)
        try:
            return generate_course(snapshot, start, spec, seed, sim.config)
        except CourseError as exc:
            raise CommandRefused("bad_command", str(exc)) from None

    def command(self, name: str, command_id: int | None, **options: Any) -> None:
        """course_start or course_stop (protocol names and fields); raises CommandRefused.
        ``through``: the course's gates (flight frame), laid elsewhere (a race: ``plan``),
        instead of a course generated here; its route is planned from this drone."""

        if name == "course_stop":
            with self.flight.lock:
                if self.run is None or self.state != "running":
                    raise CommandRefused("bad_command", "no course is running")
                self._stop(hold=True)
            return
        try:
            spec = course_spec(
                options.get("difficulty") or "medium",
                options.get("gates"),
                options.get("spacing"),
                options.get("ring_radius"),
            )
        except CourseError as exc:
            raise CommandRefused("bad_command", str(exc)) from None
        seed = options.get("seed")
        seed = secrets.randbelow(2**31) if seed is None else int(seed)
        autopilot = bool(options.get("autopilot"))
        speed = options.get("speed")
        sim = self.flight.sim
        with self.flight.lock:
            if not sim.spawned:
                raise CommandRefused("bad_command", "no drone yet: it spawns with the first map")
            mode = sim.mode
            if autopilot and mode not in _FLYING:
                raise CommandRefused(
                    "bad_command",
                    f"the autopilot needs a flying drone; it is {mode.value if mode else 'absent'}"
                    " (take off first)",
                )
            if autopilot:
                sim.command_hold(command_id=command_id)  # the course starts where it stops
            start = sim.status().T_flight_drone[:3, 3]
            snapshot = copy.deepcopy(self.flight.flight_map)
        t0 = time.perf_counter()
        through = options.get("through")
        try:
            if through is None:
                course = generate_course(snapshot, start, spec, seed, sim.config, speed)
            else:
                course = course_through(snapshot, start, through, spec, seed, sim.config, speed)
        except CourseError as exc:
            raise CommandRefused("bad_command", str(exc)) from None
        self.flight.log.info(
            "course %s seed %d: %d gates, %.1f m, par %.1f s, laid in %.0f ms",
            spec.name,
            seed,
            len(course.gates),
            course.length_m,
            course.par_s,
            (time.perf_counter() - t0) * 1e3,
        )
        with self.flight.lock:
            if self.run is not None and self.state == "running":
                self._stop(hold=self.autopilot)
            if autopilot:
                try:
                    sim.command_route(course.route, self._replanner(), command_id=command_id)
                except DroneCommandError as exc:
                    raise CommandRefused("bad_command", str(exc)) from None
            status = sim.status()
            self.run = CourseRun(course, status.time_s, status.T_flight_drone[:3, 3])
            self.state, self.autopilot, self.rank = "running", autopilot, None
            self.restart_after_crash = bool(options.get("restart_after_crash"))
            self._crashed_at = None
            self._retries = 0
            self.course_id += 1
            self.command_id = command_id
            self._speed = speed
            self._publish_state(status.time_s)

    def _replanner(self):
        """The autopilot's replan(start): the course's route from ``start`` through the gates
        left (called by the simulator, under the flight's lock, when the map changes)."""
        flight = self.flight

        def replan(start: np.ndarray):
            run = self.run
            gates = () if run is None else run.course.gates[run.next_gate :]
            if run is None or not gates:  # as the simulator expects of a planner
                raise PlanningError(Reason.UNREACHABLE, "no gate of the course is left")
            return plan_course_route(
                flight.flight_map, start, gates, run.course.lead_m, flight.config, self._speed
            )

        return replan

    def _resume_autopilot(self) -> None:
        """The autopilot's route ended early (a bump, a blocked route): fly on from here through
        the gates left, at most AUTOPILOT_RETRIES times a course; else the pilot takes over."""
        self._retries += 1
        replan = self._replanner()
        try:
            if self._retries > AUTOPILOT_RETRIES:
                raise CourseError("too many interruptions")
            route = replan(self.flight.sim.status().T_flight_drone[:3, 3])
            self.flight.sim.command_route(route, replan, command_id=self.command_id)
        except (CourseError, PlanningError, DroneCommandError) as exc:
            self.flight.log.warning("the course autopilot gives up: %s", exc)
            self.autopilot = False

    def _restart(self) -> None:
        """restart_after_crash: put the crashed drone back past the last gate it passed (or at
        the start), hovering; the run's clock ran on. An autopilot flies on from there."""
        run = self.run
        assert run is not None
        self._crashed_at = None
        point, heading = run.restart_pose()
        last = run.last_passed
        where = "the start" if last is None else f"gate {last + 1} of {len(run.course.gates)}"
        sim = self.flight.sim
        try:
            at = sim.put_back(
                point,
                float(np.arctan2(heading[1], heading[0])),
                f"put back at {where} after the crash; the clock ran on",
            )
        except DroneCommandError as exc:  # no free space there any more: the pilot takes over
            self.flight.log.warning("the course could not restart the drone: %s", exc)
            self.autopilot = False
            return
        run.restarted(sim.time_s, at)
        if self.autopilot:
            self._resume_autopilot()

    def _stop(self, hold: bool) -> None:
        """End the running course (no result); the autopilot's drone stops where it is."""
        self.state = "stopped"
        self._crashed_at = None
        if hold and self.autopilot and self.flight.sim.mode == DroneMode.GOTO:
            self.flight.sim.command_hold(command_id=self.command_id)
        self.autopilot = False
        self._publish_state(self.flight.sim.time_s)

    # ------------------------------------------------------------------ the flight thread
    def move_with_world(self, T_flight_delta: np.ndarray) -> None:
        """A corrected world (loop closure) moved the drone by ``T_flight_delta`` (4x4, flight
        frame, metres; Flight's lock held): the running course moves with it, and the next
        tick sends its course message with the moved gates. An autopilot's route was dropped by
        the move (a ``blocked`` event): the tick plans it again through the moved gates."""
        if self.run is not None and self.state == "running":
            self.run.move_with_world(T_flight_delta)
            self._sent_at = -np.inf

    def tick(self, events: list[DroneEvent]) -> list:
        """After a physics advance (``events`` are its drone events; Flight's lock held): judge
        the way since the last tick; returns DroneNotices and course messages to publish."""

        run = self.run
        if run is None or self.state != "running":
            return []
        sim = self.flight.sim
        out: list = []
        interrupted = False
        for event in events:
            if event.kind == DroneEventKind.COLLISION:
                run.collision(crash=False)
                interrupted = True  # a bump stops a goto
            elif event.kind == DroneEventKind.CRASH:
                run.collision(crash=True)
                if self.restart_after_crash:
                    self._crashed_at = event.time_s
                else:
                    self.autopilot = False  # the crash ended its route: the pilot takes over
            elif event.kind == DroneEventKind.BLOCKED:
                interrupted = True
        if self.autopilot and interrupted and sim.mode == DroneMode.HOVER:
            self._resume_autopilot()
        if self._crashed_at is not None and (
            sim.mode == DroneMode.LANDED or sim.time_s - self._crashed_at >= RESTART_AFTER_S
        ):
            self._restart()
        status = sim.status()
        gate_events = run.update(status.time_s, status.T_flight_drone[:3, 3])
        for ge in gate_events:
            out.append(
                DroneNotice(
                    DroneEventKind(ge.kind),
                    ge.time_s,
                    self.flight.to_world(ge.point),
                    self._message(ge),
                    self.command_id,
                )
            )
        if run.finished:
            self.state = "finished"
            self.rank = self._keep(run)
        if gate_events or run.finished or status.time_s - self._sent_at >= STATE_PERIOD_S:
            out.append(self.message(status.time_s))
        return out

    def _message(self, event: GateEvent) -> str:
        run = self.run
        assert run is not None
        n = len(run.course.gates)
        t = event.time_s - run.start_time_s
        if event.kind == "gate_passed":
            return f"gate {event.gate + 1} of {n} passed at {t:.2f} s"
        if event.kind == "gate_missed":
            return f"gate {event.gate + 1} of {n} missed"
        return (
            f"course finished: {run.passed} of {n} gates in {run.elapsed_s():.2f} s (par "
            f"{run.course.par_s:.2f} s), {run.bumps} bumps, {run.crashes} crashes, score "
            f"{run.score()}"
        )

    # ------------------------------------------------------------------ state and results
    def message(self, now_s: float) -> dict:
        """The ``course`` message for the current course (world frame)."""
        run = self.run
        assert run is not None
        course: Course = run.course
        rows = course.rows()
        rows[:, 0:3] = self.flight.to_world(rows[:, 0:3])
        rows[:, 3:6] = self.flight.direction_to_world(rows[:, 3:6])  # normals stay unit
        self._sent_at = now_s
        return proto.make_course(
            self.course_id,
            self.state,
            course.spec.name,
            course.seed,
            rows,
            run.states,
            run.next_gate,
            run.elapsed_s(),
            course.par_s,
            run.bumps,
            run.crashes,
            run.score(),
            self.autopilot,
            rank=self.rank if self.state == "finished" else None,
            command_id=self.command_id,
        )

    def _publish_state(self, now_s: float) -> None:
        if self.run is not None:
            message = self.message(now_s)
            self.flight.publish(message)
            self.flight.record_course(message)

    def best(self) -> list[dict[str, Any]]:
        """The session's best finished runs, best first."""
        if self._best is None:
            self._best = _ranked(read_best(self.best_path))
        return list(self._best)

    def _keep(self, run: CourseRun) -> int | None:
        """Put a finished run in the best list (and its file); its rank, or None."""
        course = run.course
        result = asdict(
            CourseResult(
                score=run.score(),
                time_s=round(run.elapsed_s(), 3),
                par_s=round(course.par_s, 3),
                gates=len(course.gates),
                passed=run.passed,
                missed=run.missed,
                bumps=run.bumps,
                crashes=run.crashes,
                difficulty=course.spec.name,
                seed=course.seed,
                autopilot=self.autopilot,
                finished_at=time.time(),
            )
        )
        ranked = _ranked([*self.best(), result])
        self._best = ranked[:BEST_KEPT]
        if self.best_path is not None:
            try:
                write_records(self.best_path, "results", self._best)
            except OSError as exc:  # the run still counts here; the disk is the store's worry
                self.flight.log.error("the course best list could not be saved: %s", exc)
        return ranked.index(result) + 1 if result in self._best else None
