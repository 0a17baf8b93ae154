"""Courses of gates in the mapped room: what a course is, and the route an autopilot flies it by.

Everything is in the flight frame (metres, z up, seconds of simulation time).

**A gate** is a ring: its centre, its unit normal (the direction the drone must fly through it)
and its radius, with a straight run of ``lead_m`` (LEAD_M) before and after it. **A course** is
its gates in order, laid from a start (course_generation.py: ``generate_course``), with the
route that flies them and that route's duration (``par_s``).

**The autopilot** flies that route (``Course.route``; ``plan_course_route`` plans it anew from
anywhere through the gates left, when the map changes): planned legs between the gates'
straight runs, joined, smoothed and timed as one route.

**The judge** (course_judge.py: ``CourseRun``) times a flight through a course and scores it.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike

from server.errors import DroneSimError
from server.geometry.arrays import FloatArray
from server.simulation.config import SimulationConfig
from server.simulation.flight_map import FlightMap
from server.simulation.planner import timed_route
from server.simulation.route import Route
from server.simulation.route_following import ROUTE_CLIMB_SHARE, plan_route

MAX_GATES = 20
LEAD_M = 0.3  # the straight run before and after each ring


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
def plan_leg(
    flight_map: FlightMap, a: FloatArray, b: FloatArray, config: SimulationConfig, speed: float
) -> FloatArray:
    """The corners (K, 3) of a planned route from a to b; raises PlanningError."""
    leg = plan_route(flight_map, a, b, config, speed)
    return np.asarray(leg.points, dtype=float)


def run_through(gate: Gate, lead_m: float) -> FloatArray:
    """(3, 3): the straight run through a gate: before, centre, after."""
    return np.stack(
        [gate.centre - lead_m * gate.normal, gate.centre, gate.centre + lead_m * gate.normal]
    )


def join_polylines(pieces: list[FloatArray]) -> FloatArray:
    """Polylines end to end, points repeated at the joins (or closer than 1 mm) dropped."""
    points: FloatArray = np.concatenate(pieces)
    keep = np.concatenate([[True], np.linalg.norm(np.diff(points, axis=0), axis=1) > 1e-3])
    joined: FloatArray = points[keep]
    return joined


def timed(
    flight_map: FlightMap, corners: FloatArray, config: SimulationConfig, speed: float
) -> Route:
    """The route along ``corners`` (K, 3) smoothed and timed with the drone's planning
    clearance and limits, at up to ``speed`` (m/s)."""
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
        run = run_through(gate, lead_m)
        along = float((here - gate.centre) @ gate.normal)
        off_axis = np.linalg.norm((here - gate.centre) - along * gate.normal)
        if k == 0 and -lead_m <= along < 0 and off_axis < 0.5 * gate.radius_m:
            pieces.append(run[1:])  # on the run already: straight on through the ring
        else:
            pieces += [plan_leg(flight_map, here, run[0], config, speed), run]
        here = run[-1]
    return timed(flight_map, join_polylines(pieces), config, speed)


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
