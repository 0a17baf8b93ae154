"""Laying a course of gates in the mapped room from the flight map's distance field.

Everything is in the flight frame (metres, z up). ``generate_course`` is seeded: one seed, map
and start give one course.

Gate centres are cells of the distance field with at least ``ring radius + drone radius +
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
through another ring would not; course_judge.judge_path). Gates are placed depth first: a gate
with no place left (after CANDIDATES_PER_GATE tries) takes the previous one back. The whole
route, legs and runs joined, smoothed and timed, is finally judged as if flown (every gate
passed, in order) and checked against the map. After MAX_TRIES places, ``CourseError`` says
why there is no course.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from server.geometry.arrays import FloatArray
from server.simulation.config import SimulationConfig
from server.simulation.course import (
    LEAD_M,
    NO_ROUTE,
    Course,
    CourseError,
    CourseSpec,
    Gate,
    join_polylines,
    plan_course_route,
    plan_leg,
    run_through,
    timed,
)
from server.simulation.course_judge import judge_path
from server.simulation.flight_map import FlightMap
from server.simulation.route import PlanningError

MAX_TRIES = 150  # places tried for gates (each plans a leg) before giving up
CANDIDATES_PER_GATE = 10  # places tried for one gate before taking the previous one back
FIRST_GATE_REACH_M = 4.0  # the first gate lies within spacing_m of the start, else up to this
RING_MARGIN_M = 0.03  # a gate's centre keeps ring radius + drone radius + this from the map
SPACING_SPREAD = 0.35  # a leg's straight length lies within +-35 % of spacing_m
MAX_PITCH_DEG = 30.0  # a gate's normal climbs or descends at most this much


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
                for part in (leg, run_through(g, lead))
            ]
            route = timed(flight_map, join_polylines(pieces), config, speed)
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
        run = run_through(gate, lead)
        if flight_map.segment_clearance(run[0], run[-1]) < config.planning_radius_m:
            why.append("no straight run through a ring")
            continue
        here = run_through(gates[-1], lead)[-1] if gates else start
        try:
            leg = plan_leg(flight_map, here, run[0], config, speed)
        except PlanningError:
            why.append("a gate the planner cannot reach")
            continue
        # The legs so far, as straight lines, must pass the gates in order (a leg through
        # another ring would not).
        polyline = join_polylines(
            [start[None]]
            + [
                p
                for g, lg in zip(gates + [gate], legs + [leg], strict=True)
                for p in (lg, run_through(g, lead))
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


def course_through(
    flight_map: FlightMap,
    start: ArrayLike,
    gates: tuple[Gate, ...],
    spec: CourseSpec,
    seed: int,
    config: SimulationConfig,
    speed_m_s: float | None = None,
) -> Course:
    """The course through ``gates`` as laid elsewhere (a shared room's race: the owner's
    gates, for every drone of the room), from this drone's ``start`` (flight frame): its route
    planned from here and its par that route's time. Raises CourseError when no route reaches
    them."""
    start = np.asarray(start, dtype=float).reshape(3)
    try:
        route = plan_course_route(flight_map, start, gates, LEAD_M, config, speed_m_s)
    except PlanningError as exc:
        raise CourseError(f"no route from this drone through the course's gates: {exc}") from None
    course = Course(spec, int(seed), tuple(gates), start.copy(), LEAD_M, route)
    return replace(course, par_s=judge_path(course, route.path, route.times).elapsed_s())
