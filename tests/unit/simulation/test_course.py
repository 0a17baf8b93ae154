"""Courses (server.simulation.course): the judge (gates passed, missed, the wrong way, score),
generation in the demo room (clearance, seen space only, reachable in order, reproducible, a clear
refusal when the room is too small) and the autopilot flying a course without collision; then the
session's side (server.sessions.runtime.course_control through Flight): course messages, gate
events, the best list on disk."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from server import protocol as proto
from server.datasets.demo import DemoSpec, _room_boxes
from server.geometry import Intrinsics
from server.sessions.errors import CommandRefused
from server.sessions.runtime.course_control import BEST_KEPT, read_best
from server.sessions.runtime.flight import Flight
from server.sessions.updates import DroneNotice
from server.simulation.config import SimulationConfig
from server.simulation.course import (
    LEAD_M,
    NO_ROUTE,
    PRESETS,
    Course,
    CourseError,
    CourseSpec,
    Gate,
    course_spec,
    plan_course_route,
)
from server.simulation.course_generation import (
    FIRST_GATE_REACH_M,
    MAX_PITCH_DEG,
    RING_MARGIN_M,
    SPACING_SPREAD,
    generate_course,
)
from server.simulation.course_judge import CourseRun, crossing
from server.simulation.drone import DroneSimulator
from server.simulation.drone_types import DroneEventKind
from server.simulation.flight_map import FlightMap
from server.simulation.planner import plan_path

CONFIG = SimulationConfig()
START = np.array([0.3, -0.6, 1.2])  # in the part of the demo room the camera "saw"


def demo_room(seen_half: bool = True) -> FlightMap:
    """The demo room (server/datasets/demo.py: 6 x 5 x 2.8 m, tables, boxes, a pillar, a shelf)
    as a flight map; with ``seen_half`` only y < 0.3 m was observed, as after a short walk."""
    rng = np.random.default_rng([DemoSpec().seed, 1])  # as build_scene draws the book sizes
    boxes = [(np.array(lo), np.array(hi)) for lo, hi, _ in _room_boxes(rng)]
    flight_map = FlightMap.from_boxes([-3.2, -2.7, -0.2], [3.2, 2.7, 3.0], boxes, CONFIG.voxel_m)
    if seen_half:
        blocked = flight_map.blocked
        occupied = blocked.copy()
        observed = np.ones(blocked.shape, dtype=bool)
        y = flight_map.cell_centres(np.argwhere(np.ones(blocked.shape, bool)))[:, 1]
        observed[~(y < 0.3).reshape(blocked.shape)] = False
        flight_map.update(flight_map.origin, occupied & observed, observed)
    return flight_map


@pytest.fixture(scope="module")
def room() -> FlightMap:
    return demo_room()


def one_gate_course(*gates: Gate, par_s: float = 10.0) -> Course:
    spec = CourseSpec("custom", len(gates), 1.0, gates[0].radius_m, 90.0)
    return Course(spec, 0, tuple(gates), np.zeros(3), 0.3, NO_ROUTE, par_s)


GATE_X = Gate(np.array([1.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0]), 0.3)  # fly along +x


# ---- the judge --------------------------------------------------------------------------------


def test_a_gate_is_passed_through_its_ring_in_its_direction():
    assert crossing(GATE_X, np.array([0.9, 0.1, 1.0]), np.array([1.1, 0.1, 1.0])) == (
        pytest.approx(0.5),
        True,
        True,
    )
    run = CourseRun(one_gate_course(GATE_X), 2.0, [0.0, 0.1, 1.0])
    assert run.update(2.5, [0.8, 0.1, 1.0]) == []  # not there yet
    events = run.update(3.0, [1.2, 0.1, 1.0])  # through the plane halfway along, 0.1 m off centre
    assert [(e.kind, e.gate) for e in events] == [("gate_passed", 0), ("course_finished", 0)]
    assert events[0].time_s == pytest.approx(2.75)
    np.testing.assert_allclose(events[0].point, [1.0, 0.1, 1.0])
    assert run.finished and run.passed == 1 and run.missed == 0
    assert run.elapsed_s() == pytest.approx(0.75)
    assert run.update(4.0, [0.0, 0.0, 1.0]) == []  # finished: nothing counts any more


def test_a_corrected_world_moves_the_gates_and_the_drone_jump_is_not_a_pass():
    """Loop closure moves the drone with its world; the gates move with it, and the jump is not
    judged: the drone just before the ring, carried 0.3 m along +x past its old place, is still
    before the moved ring (and passes it when it flies through)."""
    run = CourseRun(one_gate_course(GATE_X), 0.0, [0.9, 0.1, 1.0])
    T = np.eye(4)
    T[:3, :3] = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]  # a quarter turn about z
    T[:3, 3] = [0.3, 0.0, 0.0]
    run.move_with_world(T)
    gate = run.course.gates[0]
    np.testing.assert_allclose(gate.centre, [0.3, 1.0, 1.0], atol=1e-12)
    np.testing.assert_allclose(gate.normal, [0.0, 1.0, 0.0], atol=1e-12)
    assert gate.radius_m == GATE_X.radius_m and GATE_X.centre[0] == 1.0  # a new gate
    moved = T[:3, :3] @ np.array([0.9, 0.1, 1.0]) + T[:3, 3]  # the drone, carried
    assert run.update(1.0, moved) == []
    events = run.update(2.0, moved + [0.0, 0.2, 0.0])  # on through the moved ring
    assert [e.kind for e in events] == ["gate_passed", "course_finished"]


def test_outside_the_ring_or_the_wrong_way_is_no_pass():
    run = CourseRun(one_gate_course(GATE_X), 0.0, [0.5, 0.35, 1.0])
    assert run.update(1.0, [1.5, 0.35, 1.0]) == []  # through the plane 0.35 m off: outside
    assert run.update(2.0, [1.5, 0.0, 1.0]) == []  # in front of it now
    assert run.update(3.0, [0.5, 0.0, 1.0]) == []  # back through the ring: the wrong way
    assert run.wrong_way == 1 and run.passed == 0 and not run.finished
    assert [e.kind for e in run.update(4.0, [1.5, 0.0, 1.0])] == ["gate_passed", "course_finished"]


def test_passing_the_gate_after_the_next_marks_the_next_missed_and_further_ones_do_not_count():
    gates = [Gate(np.array([x, 0.0, 1.0]), np.array([1.0, 0.0, 0.0]), 0.3) for x in (1, 2, 3, 4)]
    course = one_gate_course(*gates)
    run = CourseRun(course, 0.0, [0.5, 1.0, 1.0])
    # Around gate 0 (y = 1 m is outside every ring), then through gate 1.
    assert run.update(1.0, [1.5, 1.0, 1.0]) == []
    assert run.update(2.0, [1.5, 0.0, 1.0]) == []
    events = run.update(3.0, [2.5, 0.0, 1.0])
    assert [(e.kind, e.gate) for e in events] == [("gate_missed", 0), ("gate_passed", 1)]
    assert run.states[:2] == ["missed", "passed"] and run.next_gate == 2
    assert run.missed == 1 and run.passed == 1 and not run.finished
    # Only the next gate and the one after it are judged: through gate 3 (x = 4) while gate 1
    # is next counts for nothing, and gate 0, passed already, neither.
    run2 = CourseRun(course, 0.0, [0.5, 0.0, 1.0])
    assert [e.kind for e in run2.update(1.0, [1.5, 0.0, 1.0])] == ["gate_passed"]
    for p in ([1.5, 1.0, 1.0], [3.5, 1.0, 1.0], [3.5, 0.0, 1.0]):  # around gates 1 and 2
        assert run2.update(2.0, p) == []
    assert run2.update(3.0, [4.5, 0.0, 1.0]) == []  # through gate 3: two ahead
    assert run2.update(4.0, [0.5, 0.0, 1.0]) == []  # back through everything: the wrong way
    assert run2.update(5.0, [1.5, 0.0, 1.0]) == []  # gate 0 again
    assert run2.next_gate == 1 and run2.passed == 1 and run2.missed == 0


def test_the_score_is_gates_penalties_and_a_time_bonus_once_finished():
    gates = [Gate(np.array([x, 0.0, 1.0]), np.array([1.0, 0.0, 0.0]), 0.3) for x in (1, 2, 3)]
    course = one_gate_course(*gates, par_s=10.0)
    run = CourseRun(course, 0.0, [0.5, 0.0, 1.0])
    run.update(1.0, [1.5, 0.0, 1.0])
    run.collision(crash=False)
    run.collision(crash=False)
    assert run.score() == 100 - 2 * 10  # running: no time bonus yet
    run.update(5.0, [1.5, 1.0, 1.0])  # around gate 1
    run.update(8.0, [2.5, 1.0, 1.0])
    run.update(10.0, [2.5, 0.0, 1.0])
    run.update(15.0, [3.5, 0.0, 1.0])  # through gate 2: gate 1 missed, finished at 12.5 s
    assert run.finished and run.passed == 2 and run.missed == 1 and run.bumps == 2
    assert run.elapsed_s() == pytest.approx(12.5)
    share = (2 * 10.0 - 12.5) / 10.0
    assert run.score() == round(2 * 100 - 50 - 2 * 10 + 50 * 3 * share)
    fast = CourseRun(course, 0.0, [0.5, 0.0, 1.0])
    fast.update(8.0, [3.5, 0.0, 1.0])  # all three in one segment, faster than par
    assert fast.passed == 3 and fast.score() == 3 * 100 + 3 * 50
    crashed = CourseRun(course, 0.0, [0.5, 0.0, 1.0])
    for _ in range(5):
        crashed.collision(crash=True)
    assert crashed.crashes == 5 and crashed.score() == 0  # never below zero


# ---- generation -------------------------------------------------------------------------------


@pytest.mark.parametrize("difficulty", sorted(PRESETS))
def test_a_generated_course_keeps_clearance_in_seen_space_and_is_reachable_in_order(
    room, difficulty
):
    spec = PRESETS[difficulty]
    course = generate_course(room, START, spec, 3, CONFIG)
    assert course.spec == spec and len(course.gates) == spec.gates and course.seed == 3
    rows = course.rows()
    centres, normals = rows[:, :3], rows[:, 3:6]
    assert np.allclose(rows[:, 6], spec.ring_radius_m)
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0)
    # Clearance: the ring plus a drone anywhere in it, with a margin for the field's error.
    clear = spec.ring_radius_m + CONFIG.radius_m + RING_MARGIN_M
    assert np.all(room.distance(centres) >= clear - 1e-6)
    # Seen space only: the whole ring lies where the camera looked (y < 0.3 m here).
    assert np.all(centres[:, 1] + spec.ring_radius_m < 0.3)
    # Spacing and steepness.
    lengths = np.linalg.norm(np.diff(centres, axis=0), axis=1)
    assert np.all(lengths <= (1 + SPACING_SPREAD) * spec.spacing_m + 1e-6)
    assert np.all(lengths >= min((1 - SPACING_SPREAD) * spec.spacing_m, 2 * LEAD_M + 0.2) - 1e-6)
    assert np.linalg.norm(centres[0] - START) <= FIRST_GATE_REACH_M
    assert np.all(np.abs(normals[:, 2]) <= math.sin(math.radians(MAX_PITCH_DEG)) + 1e-9)
    turns = np.degrees(np.arccos(np.clip(np.sum(normals[1:] * normals[:-1], axis=1), -1, 1)))
    assert np.all(turns <= spec.max_turn_deg + 1e-6)
    # Reachable in order: the planner joins each gate's straight run to the next one's.
    lead = course.lead_m
    for a, b in zip(course.gates, course.gates[1:], strict=False):
        plan_path(room, a.centre + lead * a.normal, b.centre - lead * b.normal, CONFIG.radius_m)
    # The route flies through every ring in order, clear of the map, and par is its time.
    route = course.route
    assert np.all(room.distance(route.path) >= CONFIG.radius_m)
    run = CourseRun(course, 0.0, route.path[0])
    for t, p in zip(route.times[1:], route.path[1:], strict=True):
        run.update(t, p)
    assert run.finished and run.passed == spec.gates and run.missed == 0 and run.wrong_way == 0
    assert run.elapsed_s() == pytest.approx(course.par_s)
    assert 0 < course.par_s <= route.duration_s


def test_one_seed_gives_one_course_and_another_seed_another(room):
    spec = PRESETS["medium"]
    a = generate_course(room, START, spec, 11, CONFIG)
    b = generate_course(room, START, spec, 11, CONFIG)
    c = generate_course(room, START, spec, 12, CONFIG)
    np.testing.assert_array_equal(a.rows(), b.rows())
    np.testing.assert_array_equal(a.route.path, b.route.path)
    assert not np.array_equal(a.rows(), c.rows())
    # A drone hovering a few millimetres off the place gets the same gates (the seed orders
    # the room's cells, not the ones near the start).
    for nudge in ([0.003, -0.002, 0.001], [-0.004, 0.0, 0.003]):
        d = generate_course(room, START + nudge, spec, 11, CONFIG)
        np.testing.assert_array_equal(d.rows()[:, :3], a.rows()[:, :3])
        np.testing.assert_allclose(d.rows(), a.rows(), atol=0.01)  # gate 0 faces the start


def test_explicit_numbers_replace_the_presets_and_bad_ones_are_refused():
    spec = course_spec("easy", gates=2, ring_radius_m=0.3)
    assert (spec.name, spec.gates, spec.ring_radius_m) == ("custom", 2, 0.3)
    assert spec.spacing_m == PRESETS["easy"].spacing_m
    assert course_spec("hard") is PRESETS["hard"]
    assert course_spec("hard", gates=PRESETS["hard"].gates) is PRESETS["hard"]
    for bad in ({"difficulty": "insane"}, {"gates": 0}, {"gates": 99}, {"ring_radius_m": 0.05}):
        with pytest.raises(CourseError):
            course_spec(**bad)


def test_a_room_too_small_for_the_course_is_refused_with_a_reason(room):
    closet = FlightMap.from_boxes(
        [-0.1, -0.1, -0.1], [0.7, 0.7, 2.1], [], CONFIG.voxel_m
    )  # 0.8 x 0.8 x 2.2 m: walls are the unobserved outside; no ring fits
    with pytest.raises(CourseError, match="no observed free space .* clearance"):
        generate_course(closet, [0.3, 0.3, 1.0], PRESETS["easy"], 0, CONFIG)
    cupboard = FlightMap.from_boxes([-0.1, -0.1, -0.1], [1.1, 1.1, 2.1], [], CONFIG.voxel_m)
    with pytest.raises(CourseError, match="no free place .* on from gate 0"):  # rings, no course
        generate_course(cupboard, [0.5, 0.5, 1.0], PRESETS["easy"], 0, CONFIG)
    with pytest.raises(CourseError, match="fits in the mapped room"):
        generate_course(room, START, course_spec("hard", gates=20, spacing_m=6.0), 0, CONFIG)
    with pytest.raises(CourseError, match="too tight"):
        generate_course(room, START, course_spec("easy", ring_radius_m=0.16), 0, CONFIG)
    free = FlightMap(CONFIG.voxel_m, unknown_is_free=True)
    with pytest.raises(CourseError, match="observed space only"):
        generate_course(free, START, PRESETS["easy"], 0, CONFIG)


# ---- the autopilot ----------------------------------------------------------------------------


def fly_course(drone: DroneSimulator, course: Course, max_s: float, tick_s: float = 0.05):
    """Tick like the session's flight thread: advance, then judge the way since the last tick.
    Returns the run, the drone events and the least clearance seen."""
    status = drone.status()
    run = CourseRun(course, status.time_s, status.T_flight_drone[:3, 3])
    events, least = [], math.inf
    while not run.finished and drone.time_s < max_s:
        events += drone.advance(tick_s)
        status = drone.status()
        least = min(least, status.clearance)
        run.update(status.time_s, status.T_flight_drone[:3, 3])
    return run, events, least


@pytest.mark.parametrize("difficulty, seed", [("easy", 0), ("medium", 1), ("hard", 2)])
def test_the_autopilot_flies_every_gate_without_collision(room, difficulty, seed):
    drone = DroneSimulator(CONFIG, room)
    drone.spawn(START)
    drone.advance(0.5)
    course = generate_course(
        room, drone.status().T_flight_drone[:3, 3], PRESETS[difficulty], seed, CONFIG
    )
    drone.command_route(course.route)
    run, events, least = fly_course(drone, course, 60.0)
    kinds = {e.kind for e in events}
    assert run.finished and run.passed == len(course.gates) and run.missed == 0, run.states
    assert DroneEventKind.COLLISION not in kinds and DroneEventKind.CRASH not in kinds
    assert least >= CONFIG.radius_m
    assert run.elapsed_s() <= course.par_s + 2.0  # it keeps to the route's timing
    assert run.score() >= 140 * len(course.gates)


def test_the_autopilot_replans_through_the_gates_left_when_the_route_is_blocked():
    room = demo_room(seen_half=False)  # this test changes its map
    drone = DroneSimulator(CONFIG, room)
    drone.spawn(START)
    course = generate_course(room, START, PRESETS["medium"], 4, CONFIG)
    run = CourseRun(course, 0.0, START)
    replans = []

    def replan(start):
        replans.append(run.next_gate)
        return plan_course_route(room, start, course.gates[run.next_gate :], course.lead_m, CONFIG)

    drone.command_route(course.route, replan)
    events = []
    while run.next_gate < 2:
        events += drone.advance(0.05)
        run.update(drone.time_s, drone.status().T_flight_drone[:3, 3])
    # A box appears on the route between gates 2 and 3, as far from every ring as it gets.
    path = course.route.path
    after = int(np.argmin(np.linalg.norm(path - course.gates[2].centre, axis=1)))
    ahead = path[after:]
    centres = course.rows()[:, :3]
    far = np.min(np.linalg.norm(ahead[:, None] - centres[None], axis=2), axis=1)
    spot = ahead[int(np.argmax(far))]
    assert far.max() > 0.45
    cells = np.argwhere(np.ones(room.shape, bool))
    inside = np.all(np.abs(room.cell_centres(cells) - spot) <= 0.1, axis=1)
    occupied = room.blocked.copy()
    occupied[tuple(cells[inside].T)] = True
    drone.update_map(room.origin, occupied, np.ones(room.shape, bool))
    while not run.finished and drone.time_s < 60:
        events += drone.advance(0.05)
        run.update(drone.time_s, drone.status().T_flight_drone[:3, 3])
    kinds = [e.kind for e in events]
    assert replans and replans[0] == 2  # through the gates left: 2 on
    assert DroneEventKind.REPLANNED in kinds
    assert run.finished and run.passed == len(course.gates) and run.missed == 0, run.states
    assert DroneEventKind.COLLISION not in kinds and DroneEventKind.CRASH not in kinds


# ---- the session's course (Flight) ------------------------------------------------------------


def flight_in_the_demo_room(tmp_path=None) -> tuple[Flight, list]:
    """A session's Flight (its world: an upright camera's frame, y down), fed the demo room in
    its flight frame, with a camera at START looking along flight +x; spawned there."""
    published: list = []
    K = Intrinsics(500.0, 500.0, 319.5, 239.5, 640, 480)
    flight = Flight(CONFIG, K, None, published.append, state_hz=50.0)  # gravity: camera's +y
    if tmp_path is not None:
        flight.course.best_path = tmp_path / "course_best.json"
    room = demo_room()
    observed = np.ones(room.shape, bool)  # the unobserved half stays blocked: as occupied
    flight.map_changed(room.origin, room.blocked, observed)
    R = flight.R_flight_world
    T = np.eye(4)
    T[:3, :3] = R.T @ np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]])
    T[:3, 3] = R.T @ (START - [0.8, 0.0, 0.0])
    flight.camera_moved(0, T, np.full((480, 640), 3.0, np.float32))
    flight._tick(0.02)
    assert flight.spawned
    return flight, published


def run_ticks(flight: Flight, published: list, until, max_s: float = 60.0) -> None:
    for _ in range(round(max_s / 0.05)):
        published += flight._tick(0.05)
        if until(published):
            return
    raise AssertionError(f"not within {max_s} s; last: {published[-3:]}")


def courses(published):
    return [m for m in published if isinstance(m, dict) and m.get("type") == "course"]


def test_course_start_with_autopilot_lays_flies_and_keeps_the_result(tmp_path):
    flight, published = flight_in_the_demo_room(tmp_path)
    flight.command("course_start", 7, difficulty="easy", seed=5, autopilot=True)
    first = courses(published)[0]
    assert first["state"] == "running" and first["course_id"] == 1 and first["command_id"] == 7
    assert first["difficulty"] == "easy" and first["seed"] == 5 and first["autopilot"] is True
    assert len(first["gates"]) == 7 * 3 and first["gate_states"] == ["pending"] * 3
    # World frame: this flight's world is rotated against the flight frame.
    rows = np.array(first["gates"]).reshape(-1, 7)
    centres_flight = rows[:, :3] @ flight.R_flight_world.T
    clear = PRESETS["easy"].ring_radius_m + CONFIG.radius_m + RING_MARGIN_M
    assert np.all(flight.flight_map.distance(centres_flight) >= clear - 1e-6)
    for message in courses(published):
        proto.decode(proto.encode(message))  # valid protocol messages
    run_ticks(flight, published, lambda p: any(m["state"] == "finished" for m in courses(p)))
    notices = [n for n in published if isinstance(n, DroneNotice)]
    kinds = [n.event for n in notices]
    assert kinds.count("gate_passed") == 3 and "gate_missed" not in kinds
    assert "collision" not in kinds and "crash" not in kinds
    assert kinds[-1] == "course_finished" and "score" in notices[-1].message
    assert all(n.command_id == 7 for n in notices if n.event.startswith(("gate", "course")))
    final = courses(published)[-1]
    assert final["state"] == "finished" and final["gate_states"] == ["passed"] * 3
    assert final["next_gate"] == 3 and final["rank"] == 1 and final["score"] >= 420
    assert flight.event_counts["gate_passed"] == 3
    # Kept on disk, read back as the REST route reads it.
    (best,) = read_best(tmp_path / "course_best.json")
    assert best["score"] == final["score"] and best["autopilot"] is True
    assert best["passed"] == 3 and best["seed"] == 5 and best["difficulty"] == "easy"
    assert best["time_s"] == pytest.approx(final["elapsed_s"], abs=1e-3)


def test_the_best_list_keeps_the_top_runs_best_first(tmp_path):
    flight, _ = flight_in_the_demo_room(tmp_path)
    gates = [Gate(np.array([x, 0.0, 1.0]), np.array([1.0, 0.0, 0.0]), 0.3) for x in (1, 2)]
    course = one_gate_course(*gates, par_s=5.0)
    ranks = []
    for k in range(BEST_KEPT + 3):
        run = CourseRun(course, 0.0, [0.5, 0.0, 1.0])
        run.bumps = k % 5
        run.update(3.0 + k, [2.5, 0.0, 1.0])
        ranks.append(flight.course._keep(run))
    results = read_best(tmp_path / "course_best.json")
    assert len(results) == BEST_KEPT
    scores = [r["score"] for r in results]
    assert scores == sorted(scores, reverse=True)
    assert ranks[0] == 1 and None in ranks  # the slow ones with bumps did not make the list
    assert json.loads((tmp_path / "course_best.json").read_text())["results"] == results


def test_course_commands_are_refused_clearly_when_they_cannot_be_carried_out(tmp_path):
    published: list = []
    K = Intrinsics(500.0, 500.0, 319.5, 239.5, 640, 480)
    early = Flight(CONFIG, K, None, published.append)
    with pytest.raises(CommandRefused, match="no drone yet"):
        early.command("course_start", 1)
    flight, published = flight_in_the_demo_room(tmp_path)
    with pytest.raises(CommandRefused, match="no course is running"):
        flight.command("course_stop", 2)
    with pytest.raises(CommandRefused, match="gates") as info:
        flight.command("course_start", 3, gates=20, spacing=6.0)
    assert info.value.code == "bad_command"
    flight.command("land", 4)
    run_ticks(flight, published, lambda p: any(getattr(n, "event", "") == "landed" for n in p))
    with pytest.raises(CommandRefused, match="take off first"):
        flight.command("course_start", 5, autopilot=True)
    flight.command("course_start", 6, difficulty="easy", seed=1)  # the pilot flies: fine
    flight.command("course_stop", 7)
    assert courses(published)[-1]["state"] == "stopped"


def notices(published, event: str) -> list[DroneNotice]:
    return [n for n in published if isinstance(n, DroneNotice) and n.event == event]


def crash_now(flight: Flight) -> None:
    """Throw the drone at the floor at 8 m/s: more than it can brake in its height, so the
    physics ends it in a crash (the crash speed is about 2 m/s)."""
    with flight.lock:
        flight.sim._modes.quad.vz = -8.0


def test_a_crash_in_a_race_course_puts_the_drone_back_past_the_last_gate_and_it_flies_on():
    flight, published = flight_in_the_demo_room()
    flight.command(
        "course_start", 1, difficulty="easy", seed=5, autopilot=True, restart_after_crash=True
    )
    run_ticks(flight, published, lambda p: notices(p, "gate_passed"))
    crash_now(flight)
    run_ticks(flight, published, lambda p: notices(p, "restarted"), max_s=5.0)
    (crash,) = notices(published, "crash")
    (restarted,) = notices(published, "restarted")
    assert 0.0 < restarted.timestamp - crash.timestamp <= 1.0 + 0.05
    assert "gate 1 of 3" in restarted.message
    # Hovering 0.3 m past the first gate along its normal (world frame), the clock ran on.
    gates = np.array(courses(published)[0]["gates"]).reshape(-1, 7)
    assert np.allclose(restarted.position, gates[0, :3] + 0.3 * gates[0, 3:6], atol=0.05)
    times = [m["elapsed_s"] for m in courses(published)]
    assert times == sorted(times) and courses(published)[-1]["state"] == "running"
    # The autopilot flies on from there through the gates left, and finishes.
    run_ticks(flight, published, lambda p: any(m["state"] == "finished" for m in courses(p)))
    final = courses(published)[-1]
    assert final["gate_states"] == ["passed"] * 3 and final["crashes"] == 1
    assert flight.sim.status().time_s > restarted.timestamp  # one clock, never reset


def test_without_restart_after_crash_a_crashed_drone_lands_where_it_falls():
    flight, published = flight_in_the_demo_room()
    flight.command("course_start", 1, difficulty="easy", seed=5, autopilot=True)
    run_ticks(flight, published, lambda p: notices(p, "gate_passed"))
    crash_now(flight)
    run_ticks(flight, published, lambda p: notices(p, "landed"), max_s=5.0)
    assert notices(published, "crash") and not notices(published, "restarted")
    assert courses(published)[-1]["state"] == "running" and not flight.course.autopilot


def test_a_restart_goes_past_the_last_gate_passed_even_after_a_missed_one():
    gates = [Gate(np.array([x, 0.0, 1.0]), np.array([1.0, 0.0, 0.0]), 0.3) for x in (1, 2, 3)]
    run = CourseRun(one_gate_course(*gates), 0.0, [0.0, 0.0, 1.0])
    point, heading = run.restart_pose()  # nothing passed: the start, heading for gate 1
    assert np.allclose(point, [0.0, 0.0, 1.0]) and np.allclose(heading, [1.0, 0.0, 0.0])
    run.update(0.5, [1.5, 0.0, 3.0])  # over gate 1
    run.update(1.0, [1.5, 0.0, 1.0])
    run.update(2.0, [2.5, 0.0, 1.0])  # through gate 2: gate 1 missed
    assert run.states == ["missed", "passed", "pending"] and run.last_passed == 1
    point, heading = run.restart_pose()
    assert np.allclose(point, [2.3, 0.0, 1.0]) and np.allclose(heading, [1.0, 0.0, 0.0])
    run.restarted(3.0, point)  # the jump back is not judged; the clock runs on
    assert run.states == ["missed", "passed", "pending"] and run.restarts == 1
    run.update(4.0, [3.5, 0.0, 1.0])
    assert run.finished and run.elapsed_s() == pytest.approx(3.0 + 0.7 / 1.2)  # from 2.3 m
