"""Courses of gates in the mapped room: their generation from the flight map's distance field,
the route an autopilot flies through them, and the judge that times and scores a flight.

Everything is in the flight frame (metres, z up, seconds of simulation time).

**A gate** is a ring: its centre, its unit normal (the direction the drone must fly through it)
and its radius. The drone passes it when the segment between two consecutive positions it is
judged at crosses the ring's plane from the back (``(p - centre) . normal < 0``) to the front
(``>= 0``) at a point within the radius of the centre (the drone's centre, not its whole sphere);
crossing from the front is the wrong way and counts for nothing (``wrong_way``). Gates are
taken in order: only the next gate and the one after it are judged, and passing the one after
marks the next one missed. The run finishes when every gate is passed or missed.

**Generation** (``generate_course``, seeded: one seed, map and start give one course): gate
centres are cells of the distance field with at least ``ring radius + drone radius +
RING_MARGIN_M`` of clearance, so a drone flying through the ring anywhere stays clear of the map
(the margin covers the field's error near edges); unobserved space counts as blocked, so every
ring lies in space the camera has seen. Each gate lies ``spacing_m`` (within +-35 %, and at least
the two straight runs plus 0.2 m) from the previous one (the first from the start, or farther,
up to FIRST_GATE_REACH_M, when there is no room that near), any two rings' centres at least a
ring's width plus 0.25 m apart; its normal is the direction from the previous gate (climbing or
descending at most MAX_PITCH_DEG), turned at most ``max_turn_deg`` from the previous gate's
normal. The straight run ``LEAD_M`` before and after each ring must keep the planning clearance,
and the planner must find a route from the previous gate's run (or the start) to this gate's:
reachable in order. The legs so far, as straight lines, must pass the gates in order (a leg
through another ring would not). Gates are placed depth first: a gate with no place left (after
CANDIDATES_PER_GATE tries) takes the previous one back. The whole route, legs and runs joined,
smoothed and timed, is finally judged as if flown (every gate passed, in order) and checked
against the map. After MAX_TRIES places, ``CourseError`` says why there is no course.

**The autopilot** flies that route (``Course.route``; ``plan_course_route`` plans it anew from
anywhere through the gates left, when the map changes).

**Score** (``CourseRun.score``, an integer, never below 0)::

    100 per gate passed - 50 per gate missed - 10 per bump - 100 per crash
    + time bonus (finished runs only): 50 per gate x clamp((2 par - time) / par, 0, 1)

``par`` is the duration of the course's own route at the speed it was planned for (the
autopilot's time), ``time`` the run's time from the start to its last gate: at par or faster the
full bonus, none at twice par. A clean autopilot run scores about 150 per gate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from enum import Enum

import numpy as np
from numpy.typing import ArrayLike, NDArray

from server.errors import DroneSimError
from server.geometry.arrays import FloatArray
from server.simulation.config import SimulationConfig
from server.simulation.drone import ROUTE_CLIMB_SHARE, plan_route
from server.simulation.flight_map import FlightMap
from server.simulation.planner import PlanningError, Route, timed_route

MAX_GATES = 20
MAX_TRIES = 150  # places tried for gates (each plans a leg) before giving up
CANDIDATES_PER_GATE = 10  # places tried for one gate before taking the previous one back
LEAD_M = 0.3  # the straight run before and after each ring
FIRST_GATE_REACH_M = 4.0  # the first gate lies within spacing_m of the start, else up to this
RING_MARGIN_M = 0.03  # a gate's centre keeps ring radius + drone radius + this from the map
SPACING_SPREAD = 0.35  # a leg's straight length lies within +-35 % of spacing_m
MAX_PITCH_DEG = 30.0  # a gate's normal climbs or descends at most this much

# Score (module docstring).
POINTS_PASSED = 100
POINTS_MISSED = -50
POINTS_BUMP = -10
POINTS_CRASH = -100
TIME_BONUS_PER_GATE = 50


class CourseError(DroneSimError):
    """No course of the kind asked for fits in the mapped room, or the settings are bad."""


@dataclass(frozen=True)
class Gate:
    """A ring: ``centre`` (3,) and unit ``normal`` (3,), the way to fly through, metres."""

    centre: FloatArray
    normal: FloatArray
    radius_m: float

    def as_row(self) -> list[float]:
        """[cx, cy, cz, nx, ny, nz, radius]."""
        return [*map(float, self.centre), *map(float, self.normal), float(self.radius_m)]


@dataclass(frozen=True)
class CourseSpec:
    """What the pilot asks for: ``gates`` rings of ``ring_radius_m``, ``spacing_m`` apart
    (straight-line distance between consecutive centres, +-35 %), each turned at most
    ``max_turn_deg`` from the previous one's direction (tightness)."""

    name: str
    gates: int
    spacing_m: float
    ring_radius_m: float
    max_turn_deg: float

    def __post_init__(self) -> None:
        if not 1 <= self.gates <= MAX_GATES:
            raise CourseError(f"a course has 1 to {MAX_GATES} gates, not {self.gates}")
        if not 0.5 <= self.spacing_m <= 6.0:
            raise CourseError(f"gate spacing must be 0.5 to 6 m, not {self.spacing_m}")
        if not 0.15 <= self.ring_radius_m <= 0.7:
            raise CourseError(f"ring radius must be 0.15 to 0.7 m, not {self.ring_radius_m}")
        if not 0 <= self.max_turn_deg <= 150:
            raise CourseError(f"max turn must be 0 to 150 degrees, not {self.max_turn_deg}")


PRESETS: dict[str, CourseSpec] = {
    "easy": CourseSpec("easy", gates=3, spacing_m=1.2, ring_radius_m=0.3, max_turn_deg=120.0),
    "medium": CourseSpec("medium", gates=5, spacing_m=1.0, ring_radius_m=0.25, max_turn_deg=135.0),
    "hard": CourseSpec("hard", gates=7, spacing_m=0.9, ring_radius_m=0.2, max_turn_deg=150.0),
}


def course_spec(
    difficulty: str = "medium",
    gates: int | None = None,
    spacing_m: float | None = None,
    ring_radius_m: float | None = None,
    max_turn_deg: float | None = None,
) -> CourseSpec:
    """A preset (easy, medium, hard), with any of its numbers replaced (then named custom)."""
    if difficulty not in PRESETS:
        raise CourseError(f"difficulty must be one of {sorted(PRESETS)}, not {difficulty!r}")
    base = PRESETS[difficulty]
    given = {
        "gates": gates,
        "spacing_m": spacing_m,
        "ring_radius_m": ring_radius_m,
        "max_turn_deg": max_turn_deg,
    }
    changed = {k: v for k, v in given.items() if v is not None and v != getattr(base, k)}
    if not changed:
        return base
    values = {k: getattr(base, k) for k in given} | changed
    return CourseSpec(
        "custom", int(values.pop("gates")), **{k: float(v) for k, v in values.items()}
    )


@dataclass(frozen=True)
class Course:
    """Gates in order, with the route that flies them from ``start`` (the autopilot's) and its
    duration at the planned speed (``par_s``)."""

    spec: CourseSpec
    seed: int
    gates: tuple[Gate, ...]
    start: FloatArray
    lead_m: float  # straight run before and after each ring
    route: Route = field(repr=False)
    par_s: float = 0.0  # when the route passes its last gate, s after the start

    @property
    def length_m(self) -> float:
        return float(self.route.length_m)

    def moved(self, T: FloatArray) -> Course:
        """This course carried by ``T`` (4x4, flight frame, metres): its gates and start where
        a corrected world (loop closure) puts the places they were laid at. The autopilot's
        route is not carried: it is planned again through the moved gates on the new map."""
        R, t = np.asarray(T, dtype=float)[:3, :3], np.asarray(T, dtype=float)[:3, 3]
        gates = tuple(Gate(R @ g.centre + t, R @ g.normal, g.radius_m) for g in self.gates)
        return replace(self, gates=gates, start=R @ self.start + t)

    def rows(self) -> FloatArray:
        """(N, 7): centre, normal, radius per gate."""
        return np.array([g.as_row() for g in self.gates], dtype=float).reshape(-1, 7)


# --- routes through gates ----------------------------------------------------------------------
def _plan_leg(
    flight_map: FlightMap, a: FloatArray, b: FloatArray, config: SimulationConfig, speed: float
) -> FloatArray:
    """The corners (K, 3) of a planned route from a to b; raises PlanningError."""
    leg = plan_route(flight_map, a, b, config, speed)
    return np.asarray(leg.points, dtype=float)


def _run_through(gate: Gate, lead_m: float) -> FloatArray:
    """(3, 3): the straight run through a gate: before, centre, after."""
    return np.stack(
        [gate.centre - lead_m * gate.normal, gate.centre, gate.centre + lead_m * gate.normal]
    )


def _join(pieces: list[FloatArray]) -> FloatArray:
    """Polylines end to end, points repeated at the joins (or closer than 1 mm) dropped."""
    points: FloatArray = np.concatenate(pieces)
    keep = np.concatenate([[True], np.linalg.norm(np.diff(points, axis=0), axis=1) > 1e-3])
    joined: FloatArray = points[keep]
    return joined


def _timed(
    flight_map: FlightMap, corners: FloatArray, config: SimulationConfig, speed: float
) -> Route:
    return timed_route(
        flight_map,
        corners,
        config.planning_radius_m,
        speed,
        config.route_accel_m_s2,
        ROUTE_CLIMB_SHARE * config.max_climb_rate_m_s,
    )


def plan_course_route(
    flight_map: FlightMap,
    start: ArrayLike,
    gates: list[Gate] | tuple[Gate, ...],
    lead_m: float,
    config: SimulationConfig,
    speed_m_s: float | None = None,
) -> Route:
    """A timed route from ``start`` through ``gates`` in order (each along its normal, straight
    for ``lead_m`` on either side), ending ``lead_m`` past the last; raises PlanningError. A
    start already on the straight run of the first gate flies on from there."""
    speed = config.cruise_speed_m_s if speed_m_s is None else float(speed_m_s)
    here = np.asarray(start, dtype=float).reshape(3)
    pieces = [here[None]]
    for k, gate in enumerate(gates):
        run = _run_through(gate, lead_m)
        along = float((here - gate.centre) @ gate.normal)
        off_axis = np.linalg.norm((here - gate.centre) - along * gate.normal)
        if k == 0 and -lead_m <= along < 0 and off_axis < 0.5 * gate.radius_m:
            pieces.append(run[1:])  # on the run already: straight on through the ring
        else:
            pieces += [_plan_leg(flight_map, here, run[0], config, speed), run]
        here = run[-1]
    return _timed(flight_map, _join(pieces), config, speed)


NO_ROUTE = Route(
    np.zeros((1, 3)),
    np.zeros((1, 3)),
    np.zeros(1),
    np.zeros(1),
    0.0,
    0.0,
    np.zeros((1, 3)),
    np.zeros((1, 3)),
)  # a draft course's, while its gates are being placed


# --- the judge ---------------------------------------------------------------------------------
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
        self.finished_at_s: float | None = None
        self._last = np.asarray(position, dtype=float).reshape(3).copy()
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


def _mix(x: NDArray[np.uint64]) -> NDArray[np.uint64]:
    """SplitMix64's finaliser on uint64 (wrapping arithmetic): a well-spread hash."""
    x = x + np.uint64(0x9E3779B97F4A7C15)
    x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    mixed: NDArray[np.uint64] = x ^ (x >> np.uint64(31))
    return mixed


def _priorities(centres: FloatArray, voxel_m: float, seed: int, level: int) -> NDArray[np.uint64]:
    """(N,) uint64: the order in which places (cell centres, flight frame) are tried for gate
    ``level`` under ``seed``: a hash of the seed, the level and each cell's lattice position,
    so a cell keeps its place in the order however the grid around it grows."""
    ijk = np.floor(np.asarray(centres) / voxel_m).astype(np.int64).astype(np.uint64)
    with np.errstate(over="ignore"):
        h = _mix(np.full(len(ijk), (int(seed) << 8) + int(level), dtype=np.uint64))
        for axis in range(3):
            h = _mix(h ^ ijk[:, axis])
    return h


# --- generation --------------------------------------------------------------------------------
def generate_course(
    flight_map: FlightMap,
    start: ArrayLike,
    spec: CourseSpec,
    seed: int,
    config: SimulationConfig,
    speed_m_s: float | None = None,
) -> Course:
    """A course of ``spec`` starting at ``start`` (where the drone is; flight frame), the same
    for the same map, start, spec and ``seed`` (module docstring); raises CourseError when the
    mapped room has no room for it."""
    if flight_map.unknown_is_free:
        raise CourseError(
            "courses are laid in observed space only: the simulation treats unobserved space "
            "as free here (unknown_is_free), so a course cannot tell it apart"
        )
    start = np.asarray(start, dtype=float).reshape(3)
    speed = config.cruise_speed_m_s if speed_m_s is None else float(speed_m_s)
    if config.radius_m * 1.5 > spec.ring_radius_m:
        raise CourseError(
            f"rings of {spec.ring_radius_m:.2f} m are too tight for a drone of "
            f"{config.radius_m:.2f} m radius (at least 1.5 times it)"
        )
    required = spec.ring_radius_m + config.radius_m + RING_MARGIN_M
    if required > flight_map.max_distance_m - flight_map.voxel_m:
        raise CourseError(
            f"rings of {spec.ring_radius_m:.2f} m need {required:.2f} m of clearance, beyond "
            f"what the flight map measures ({flight_map.max_distance_m:.2f} m)"
        )
    if 0 in flight_map.shape:
        raise CourseError("the room is not mapped yet")
    cells = np.argwhere(flight_map.esdf >= required)
    if len(cells) == 0:
        raise CourseError(
            f"no observed free space has {required:.2f} m of clearance all round (a ring of "
            f"{spec.ring_radius_m:.2f} m plus the drone and its margin): map more of the room, "
            "or pick an easier course (smaller rings)"
        )
    candidates = flight_map.cell_centres(cells)
    why: list[str] = []
    course = _search(flight_map, start, spec, seed, config, speed, candidates, LEAD_M, why)
    if course is not None:
        return course
    reasons = "; ".join(sorted(set(why))[:3]) or "no place fits"
    raise CourseError(
        f"no {spec.name} course ({spec.gates} gates of {spec.ring_radius_m:.2f} m, "
        f"{spec.spacing_m:.1f} m apart) fits in the mapped room near the drone ({reasons}): "
        "map more of the room, or pick an easier course"
    )


def _search(
    flight_map: FlightMap,
    start: FloatArray,
    spec: CourseSpec,
    seed: int,
    config: SimulationConfig,
    speed: float,
    candidates: FloatArray,
    lead: float,
    why: list[str],
) -> Course | None:
    """Depth-first: place gate after gate, each among up to CANDIDATES_PER_GATE places (in the
    seed's order, ``_priorities``); a gate with no place left takes the previous one back. At
    most MAX_TRIES places are tried (each plans a leg). None (reasons in ``why``) when no
    course came."""
    lo = max((1 - SPACING_SPREAD) * spec.spacing_m, 2 * lead + 0.2)
    hi = max((1 + SPACING_SPREAD) * spec.spacing_m, lo + 0.2)
    apart = max(2 * spec.ring_radius_m + 0.25, 0.6)  # any two rings' centres
    max_z = math.sin(math.radians(MAX_PITCH_DEG))
    min_cos_turn = math.cos(math.radians(spec.max_turn_deg))

    def options(gates: list[Gate]) -> list[tuple[FloatArray, FloatArray]]:
        previous = gates[-1].centre if gates else start
        offset = candidates - previous
        dist = np.linalg.norm(offset, axis=1)
        direction = offset / np.maximum(dist, 1e-9)[:, None]
        ok = (dist >= lo) & (np.abs(direction[:, 2]) <= max_z)
        if gates:
            ok &= direction @ gates[-1].normal >= min_cos_turn - 1e-9
        for g in gates:
            ok &= np.linalg.norm(candidates - g.centre, axis=1) >= apart
        # The first gate may lie farther when the drone is in a cramped corner of the map.
        for reach in (
            (hi,) if gates else (hi, max(2 * hi, FIRST_GATE_REACH_M / 2), FIRST_GATE_REACH_M)
        ):
            near = ok & (dist <= reach)
            if near.any():
                break
        # In the seed's order of the cells (stable when the start moves a little or the map
        # grows elsewhere): the same map, start and seed give the same course.
        allowed = np.flatnonzero(near)
        level = _priorities(candidates[allowed], flight_map.voxel_m, seed, len(gates))
        picks = allowed[np.argsort(level, kind="stable")][:CANDIDATES_PER_GATE]
        if len(picks) == 0:
            why.append(f"no free place {lo:.1f}-{hi:.1f} m on from gate {len(gates)}")
        return [(candidates[i], direction[i]) for i in picks[::-1]]  # popped from the end

    gates: list[Gate] = []
    legs: list[FloatArray] = []
    left = [options(gates)]
    tries = 0
    while True:
        if len(gates) == spec.gates:
            pieces = [start[None]] + [
                part
                for g, leg in zip(gates, legs, strict=True)
                for part in (leg, _run_through(g, lead))
            ]
            route = _timed(flight_map, _join(pieces), config, speed)
            course = Course(spec, int(seed), tuple(gates), start.copy(), lead, route)
            judged = judge_path(course, route.path, route.times)
            if (
                judged.finished
                and judged.passed == len(gates)
                and float(flight_map.distance(route.path).min()) >= config.radius_m
            ):
                return replace(course, par_s=judged.elapsed_s())
            why.append("the smoothed route missed a ring")
            gates.pop(), legs.pop(), left.pop()
            continue
        if not left[-1]:
            if not gates:
                return None
            gates.pop(), legs.pop(), left.pop()
            continue
        tries += 1
        if tries > MAX_TRIES:
            why.append(f"{MAX_TRIES} places tried")
            return None
        centre, normal = left[-1].pop()
        gate = Gate(centre.copy(), normal.copy(), spec.ring_radius_m)
        run = _run_through(gate, lead)
        if flight_map.segment_clearance(run[0], run[-1]) < config.planning_radius_m:
            why.append("no straight run through a ring")
            continue
        here = _run_through(gates[-1], lead)[-1] if gates else start
        try:
            leg = _plan_leg(flight_map, here, run[0], config, speed)
        except PlanningError:
            why.append("a gate the planner cannot reach")
            continue
        # The legs so far, as straight lines, must pass the gates in order (a leg through
        # another ring would not).
        polyline = _join(
            [start[None]]
            + [
                p
                for g, lg in zip(gates + [gate], legs + [leg], strict=True)
                for p in (lg, _run_through(g, lead))
            ]
        )
        draft = Course(spec, int(seed), (*gates, gate), start, lead, NO_ROUTE)
        judged = judge_path(draft, polyline)
        if not (judged.finished and judged.passed == len(gates) + 1):
            why.append("a leg crossed another ring")
            continue
        gates.append(gate)
        legs.append(leg)
        left.append(options(gates))
