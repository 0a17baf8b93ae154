"""Physics benchmark: simulated steps per second of one drone on one core.

Cases, from the bare dynamics up to the whole per-session simulator as the server runs it
(``advance`` in frame-sized slices, collision checks every physics step included):

- ``quadrotor``: ``Quadrotor.step`` with constant motor commands.
- ``quadrotor + controller``: the cascaded controller holding a hover setpoint.
- ``simulator hover``: ``DroneSimulator.advance`` hovering in the open (where it spawned: a
  drone holding still skips its steps, server/simulation/stillness.py, so this is the cost
  of skipping; benchmarks/drone_physics.py sets it against stepping every step).
- ``simulator goto``: planned routes through the door of ``room_with_door``, back and forth
  (planning time excluded: only ``advance`` is timed).
- ``simulator on a wall``: full pitch into a wall, the worst case for collision queries (every
  step is within reach of the wall, so every step queries the distance field).
- ``simulator angle`` / ``simulator acro``: the pilot's flight modes (pilot_modes.py) turning
  on the spot with the yaw stick at half, sticks sent at 20 Hz as the page does.
- ``simulator on a wall``: pushing into a wall below the crash speed, bumping again and again:
  the worst case for collision queries (every step is within reach of the wall, so every step
  queries the distance field, and contacts rewind).
- ``simulator course``: the autopilot flying medium courses (server/simulation/course.py) in
  the demo room (server/datasets/demo.py), judged after every frame slice as the session does
  (``CourseRun.update`` on the drone's status, timed with ``advance``); a finished course is
  followed by a new one from where the drone is (laying it is not timed: it happens once per
  course_start, on the command's thread).

Prints steps per second and microseconds per step, both per CPU second of this process (what
one core delivers, even when other jobs share the machine) and per wall second, and the
real-time factor at the configured physics rate against the target (>= 20x, judged on CPU
time); appends the table to ``benchmarks/results/physics.md``.

    python benchmarks/physics.py [--seconds S]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # one core: numpy must not fan out

import argparse  # noqa: E402
import datetime  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from rich.console import Console  # noqa: E402
from rich.table import Table  # noqa: E402

from server.datasets.demo import DemoSpec, _room_boxes  # noqa: E402
from server.simulation.config import SimulationConfig  # noqa: E402
from server.simulation.control import (  # noqa: E402
    CascadedController,
    ControlGains,
    ControlLimits,
    Setpoint,
)
from server.simulation.course import PRESETS  # noqa: E402
from server.simulation.course_generation import generate_course  # noqa: E402
from server.simulation.course_judge import CourseRun  # noqa: E402
from server.simulation.drone import DroneSimulator  # noqa: E402
from server.simulation.drone_types import DroneEventKind  # noqa: E402
from server.simulation.flight_map import FlightMap  # noqa: E402
from server.simulation.quadrotor import Quadrotor, QuadrotorParams  # noqa: E402
from server.simulation.scenes import room_with_door  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results" / "physics.md"
TARGET_RTF = 20.0
FRAME_S = 1.0 / 30.0  # the server advances the simulator once per frame or so
console = Console(width=max(Console().width, 130))  # whole table, also when piped


def bench_quadrotor(config: SimulationConfig, steps: int) -> tuple[int, float, float]:
    params = QuadrotorParams.from_config(config)
    quad = Quadrotor(params, config.dt_s)
    f = params.hover_thrust_n
    wall, cpu = time.perf_counter(), time.process_time()
    for _ in range(steps):
        quad.step(f, f, f, f)
    return steps, time.perf_counter() - wall, time.process_time() - cpu


def bench_controller(config: SimulationConfig, steps: int) -> tuple[int, float, float]:
    params = QuadrotorParams.from_config(config)
    quad = Quadrotor(params, config.dt_s)
    ctrl = CascadedController(
        params, ControlGains.from_config(config), ControlLimits.from_config(config)
    )
    sp = Setpoint((0.3, -0.2, 0.1), 0.5)  # a small step, then hover
    wall, cpu = time.perf_counter(), time.process_time()
    for _ in range(steps):
        quad.step(*ctrl.update(quad, sp))
    return steps, time.perf_counter() - wall, time.process_time() - cpu


def _timed_advance(
    drone: DroneSimulator,
    seconds: float,
    between: Callable[[DroneSimulator], None] | None = None,
    events: list | None = None,
):
    """Advance in frame slices for ``seconds`` of simulated time; only advance() is timed. The
    events advance() hands back (once: it forgets them) are added to ``events``."""
    steps0, wall_s, cpu_s = drone.time_s, 0.0, 0.0
    while drone.time_s - steps0 < seconds:
        if between is not None:
            between(drone)
        wall, cpu = time.perf_counter(), time.process_time()
        happened = drone.advance(FRAME_S)
        wall_s += time.perf_counter() - wall
        cpu_s += time.process_time() - cpu
        if events is not None:
            events += happened
    return round((drone.time_s - steps0) / drone.config.dt_s), wall_s, cpu_s


def bench_hover(config: SimulationConfig, seconds: float):
    scene = room_with_door(config.voxel_m)
    drone = DroneSimulator(config, scene.flight_map)
    drone.spawn(scene.start)
    return _timed_advance(drone, seconds)


def bench_goto(config: SimulationConfig, seconds: float):
    scene = room_with_door(config.voxel_m)
    drone = DroneSimulator(config, scene.flight_map)
    drone.spawn(scene.start)
    ends = [scene.goal, scene.start]
    events: list = []

    def next_route(d: DroneSimulator) -> None:
        if d.mode.value != "goto":
            d.command_goto(ends[0], speed=2.0)
            ends.reverse()

    steps, wall, cpu = 0, 0.0, 0.0
    while steps * config.dt_s < seconds:
        next_route(drone)
        s, w, c = _timed_advance(drone, FRAME_S, events=events)
        steps, wall, cpu = steps + s, wall + w, cpu + c
    if any(e.kind == DroneEventKind.COLLISION for e in events):
        console.print("[red]the goto case collided[/red]")
    return steps, wall, cpu


def bench_wall(config: SimulationConfig, seconds: float):
    scene = room_with_door(config.voxel_m)
    drone = DroneSimulator(config, scene.flight_map)
    drone.spawn([1.6, 0.6, 1.2])  # 0.3 m from the wall's face, facing it
    # 0.35 of full pitch: about 1 m/s into the wall, below crash_speed_m_s (a crash would end
    # the pushing: the drone would lie on the floor, which costs nothing).
    events: list = []
    result = _timed_advance(
        drone, seconds, lambda d: d.command_sticks((0.0, 0.0, 0.35, 0.0)), events=events
    )
    if any(e.kind == DroneEventKind.CRASH for e in events):
        console.print("[red]the wall case crashed: it measured a drone at rest[/red]")
    return result


def demo_room(config: SimulationConfig) -> FlightMap:
    """The demo room (6 x 5 x 2.8 m, furniture) as a flight map, all of it observed."""
    rng = np.random.default_rng([DemoSpec().seed, 1])
    boxes = [(np.array(lo), np.array(hi)) for lo, hi, _ in _room_boxes(rng)]
    return FlightMap.from_boxes([-3.2, -2.7, -0.2], [3.2, 2.7, 3.0], boxes, config.voxel_m)


def bench_course(config: SimulationConfig, seconds: float):
    flight_map = demo_room(config)
    drone = DroneSimulator(config, flight_map)
    drone.spawn([0.3, -0.6, 1.2])
    steps, wall_s, cpu_s, seed, courses, passed = 0, 0.0, 0.0, 0, 0, 0
    events: list = []
    run = None
    laid_s = []
    while steps * config.dt_s < seconds:
        if run is None or run.finished:
            if run is not None:
                passed += run.passed
            here = drone.status().T_flight_drone[:3, 3]
            t = time.perf_counter()
            course = generate_course(flight_map, here, PRESETS["medium"], seed, config)
            laid_s.append(time.perf_counter() - t)
            drone.command_route(course.route)
            run = CourseRun(course, drone.time_s, here)
            seed, courses = seed + 1, courses + 1
        t0 = drone.time_s
        wall, cpu = time.perf_counter(), time.process_time()
        events += drone.advance(FRAME_S)
        status = drone.status()
        run.update(status.time_s, status.T_flight_drone[:3, 3])
        wall_s += time.perf_counter() - wall
        cpu_s += time.process_time() - cpu
        steps += round((drone.time_s - t0) / config.dt_s)
    if any(e.kind in (DroneEventKind.COLLISION, DroneEventKind.CRASH) for e in events):
        console.print("[red]the course case collided[/red]")
    console.print(
        f"course case: {courses} medium courses flown, {passed} gates passed; laying one took "
        f"{1e3 * np.mean(laid_s):.0f} ms on average, {1e3 * max(laid_s):.0f} ms at most "
        "(not in the figures below)"
    )
    return steps, wall_s, cpu_s


def bench_flight_mode(config: SimulationConfig, seconds: float, mode: str):
    scene = room_with_door(config.voxel_m)
    drone = DroneSimulator(config, scene.flight_map)
    drone.spawn(scene.start)
    drone.set_flight_mode(mode)
    sent = [-1.0]

    def sticks(d: DroneSimulator) -> None:
        if d.time_s - sent[0] >= 0.05:
            d.command_sticks((0.0, 0.5, 0.0, 0.0))
            sent[0] = d.time_s

    return _timed_advance(drone, seconds, sticks)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--seconds", type=float, default=30.0, help="simulated seconds per case (default 30)"
    )
    args = parser.parse_args(argv)
    config = SimulationConfig()
    n = round(args.seconds * config.physics_hz)
    cases = [
        ("quadrotor", lambda: bench_quadrotor(config, n)),
        ("quadrotor + controller", lambda: bench_controller(config, n)),
        ("simulator hover", lambda: bench_hover(config, args.seconds)),
        ("simulator goto", lambda: bench_goto(config, args.seconds)),
        ("simulator on a wall", lambda: bench_wall(config, args.seconds)),
        ("simulator angle", lambda: bench_flight_mode(config, args.seconds, "angle")),
        ("simulator acro", lambda: bench_flight_mode(config, args.seconds, "acro")),
        ("simulator course", lambda: bench_course(config, args.seconds)),
    ]
    table = Table(
        title=f"Physics, one drone, one core, {config.physics_hz} Hz "
        f"({args.seconds:g} simulated s per case)"
    )
    columns = (
        "case",
        "steps",
        "steps/CPU-s",
        "us/step (CPU)",
        "real-time factor (CPU)",
        "steps/wall-s",
        "cpu/wall",
        f">= {TARGET_RTF:g}x",
    )
    for column in columns:
        table.add_column(column, justify="left" if column == "case" else "right")
    rows = []
    for name, run in cases:
        steps, wall, cpu = run()
        rate = steps / cpu
        rtf = rate / config.physics_hz
        row = (
            name,
            f"{steps}",
            f"{rate:,.0f}",
            f"{1e6 / rate:.1f}",
            f"{rtf:.1f}x",
            f"{steps / wall:,.0f}",
            f"{cpu / wall:.2f}",
            "✓" if rtf >= TARGET_RTF else "✗",
        )
        rows.append((row, rtf))
        table.add_row(*row)
    console.print(table)

    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    with RESULTS.open("a") as out:
        out.write(
            f"\n## {datetime.datetime.now().isoformat(timespec='seconds')}, "
            f"{platform.platform()}, {platform.processor() or platform.machine()}, "
            f"Python {platform.python_version()}, numpy {np.__version__}\n\n"
            f"`python {' '.join(['benchmarks/physics.py', *sys.argv[1:]])}`, "
            f"{config.physics_hz} Hz, {args.seconds:g} simulated s per case\n\n"
            f"| {' | '.join(columns)} |\n|---|{'--:|' * (len(columns) - 2)}:-:|\n"
        )
        for row, _ in rows:
            out.write(f"| {' | '.join(row)} |\n")
    console.print(f"appended to {RESULTS}")
    return 0 if all(rtf >= TARGET_RTF for _, rtf in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
