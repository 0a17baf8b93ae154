"""Planning benchmark: routes in flight maps fused from real RGB-D sequences.

Per sequence: every ``--every``-th frame is fused into a TSDF map at its ground-truth pose, the
map's occupancy grid (5 cm) becomes a ``FlightMap``, and ``--pairs`` random start/goal pairs
drawn (seeded) among the cells with the planning clearance are planned with the drone's own
settings (``SimulationConfig``: radius 0.12 m + margin 0.08 m, cruise speed, route
acceleration, climb rate). Then every route is flown by ``DroneSimulator`` (``fly_routes``),
which counts collisions and physics steps per second.

Frames: the flight frame is the dataset's world frame with its axes permuted so that z is the
world axis nearest to the cameras' mean "up" (``server.evaluation.plots.up_direction``); these
datasets record no gravity, so "up" is only as good as that axis.

Figures: ESDF build time (full, and incremental after one more fused frame); success rate
over all pairs, and over the pairs that the 5 cm grid connects (labelled independently of the
planner, ``scipy.ndimage.label``); planning ms p50/p95/max (the first query, which builds the
search lattice, is reported apart); route length over straight-line length; collisions and
arrivals in flight; physics steps per second (real-time factor).

    python benchmarks/planning.py                          # both sequences, 1000 pairs each
    python benchmarks/planning.py ../shared/data/synthetic_room0 --pairs 200 --fly 50

Prints one table (figures beside their targets), appends it to <out>/planning.md, updates
<out>/planning.json and writes <out>/planning_<sequence>.png (top view, a few routes).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # one core: numpy must not fan out

import argparse  # noqa: E402
import datetime  # noqa: E402
import json  # noqa: E402
import logging  # noqa: E402
import platform  # noqa: E402
import shlex  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import matplotlib  # noqa: E402
import numpy as np  # noqa: E402
from rich.console import Console  # noqa: E402
from rich.table import Table  # noqa: E402
from scipy import ndimage  # noqa: E402
from tqdm import tqdm  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

REPO_ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO_ROOT))

from server.datasets import open_dataset  # noqa: E402
from server.errors import DroneSimError  # noqa: E402
from server.evaluation.plots import top_view_basis, up_direction  # noqa: E402
from server.mapping.tsdf import TSDFMap  # noqa: E402
from server.pipeline import ground_truth_pose_at  # noqa: E402
from server.simulation.config import SimulationConfig  # noqa: E402
from server.simulation.drone import DroneSimulator  # noqa: E402
from server.simulation.drone_types import DroneEventKind  # noqa: E402
from server.simulation.flight_map import FlightMap  # noqa: E402
from server.simulation.route import PlanningError  # noqa: E402
from server.simulation.route_following import plan_route  # noqa: E402

DATA = REPO_ROOT.parent / "shared" / "data"
SEQUENCES = ("synthetic_room0", "7scenes_a")
console = Console(width=max(Console().width, 120))
log = logging.getLogger("benchmarks.planning")

# (key, label, target text, test) for the figures that have a target.
TARGETS = {
    "plan_ms_p95": ("<= 20 ms", lambda v: v <= 20.0),
    "success_connected": ("100 %", lambda v: v >= 100.0),
    "collisions": ("0", lambda v: v == 0),
    "realtime_factor": (">= 20x", lambda v: v >= 20.0),
}


# --- map -----------------------------------------------------------------------------------
def fuse_flight_map(path: Path, every: int, voxel_m: float, config: SimulationConfig) -> dict:
    """Fuse every ``every``-th frame at ground truth; the flight map of all but the last fused
    frame, then the last one added incrementally (both timed)."""
    dataset = open_dataset(path)
    frames, poses = [], []
    for i in range(0, len(dataset), every):
        frame = dataset[i]
        pose = ground_truth_pose_at(dataset, frame.timestamp)
        if pose is not None:
            frames.append(i)
            poses.append(pose)
    poses = np.array(poses)
    up = up_direction(poses)
    R_flight_world = np.vstack([top_view_basis(up), up])  # right-handed, z = up
    tsdf = TSDFMap()
    flight_map = FlightMap(voxel_m, config.unknown_is_free)
    timings = {}
    for n, (i, pose) in enumerate(
        tqdm(list(zip(frames, poses, strict=True)), desc=f"fuse {path.name}", unit="frame")
    ):
        frame = dataset[i]
        tsdf.integrate(frame.colour, frame.depth, dataset.intrinsics, pose)
        if n >= len(frames) - 2:  # the map before and after the last frame
            grid = tsdf.occupancy(voxel_m, R_grid_world=R_flight_world)
            start = time.process_time()
            flight_map.update(*grid)
            key = "esdf_full_ms" if n == len(frames) - 2 else "esdf_incremental_ms"
            timings[key] = (time.process_time() - start) * 1e3
    check = FlightMap(voxel_m, config.unknown_is_free)
    check.update(*grid)
    assert np.array_equal(check.esdf, flight_map.esdf), "incremental ESDF differs from a rebuild"
    return {"flight_map": flight_map, "occupied": grid[1], "frames_fused": len(frames), **timings}


def connected_in_grid(flight_map: FlightMap, clearance_m: float, a: np.ndarray, b: np.ndarray):
    """(N,) bool: pairs whose cells are 26-connected through cells with the clearance, on the
    map's own 5 cm grid (independent of the planner's lattice)."""
    labels = ndimage.label(flight_map.esdf >= clearance_m, structure=np.ones((3, 3, 3)))[0]

    def label(p):
        ijk = np.floor((p - flight_map.origin) / flight_map.voxel_m).astype(int)
        return labels[tuple(ijk.T)]

    la, lb = label(a), label(b)
    return (la == lb) & (la > 0)


# --- planning ------------------------------------------------------------------------------
def plan_pairs(flight_map: FlightMap, starts, goals, config: SimulationConfig, name: str):
    """Plan every pair with the drone's settings; per pair: ok, reason, ms, length, route."""
    results = []
    for start, goal in tqdm(
        list(zip(starts, goals, strict=True)), desc=f"plan {name}", unit="route"
    ):
        t0, c0 = time.perf_counter(), time.process_time()
        try:
            route = plan_route(flight_map, start, goal, config, config.cruise_speed_m_s)
            reason = None
        except PlanningError as exc:
            route, reason = None, exc.reason.value
        results.append(
            {
                "ms": (time.perf_counter() - t0) * 1e3,
                "cpu_ms": (time.process_time() - c0) * 1e3,
                "route": route,
                "reason": reason,
                "start": start.tolist(),
                "goal": goal.tolist(),
            }
        )
    return results


# --- flying ------------------------------------------------------------------------------------
def fly_routes(
    flight_map: FlightMap,
    pairs: list[tuple[np.ndarray, np.ndarray, float]],
    config: SimulationConfig,
    name: str,
) -> dict:
    """Fly each (start, goal, planned duration s) with ``DroneSimulator``:
    spawn at start, goto goal (the simulator plans with the same planner), advance in 1/30 s
    slices until it arrives or twice the planned duration (plus 5 s) runs out. Returns
    collisions, arrivals, timeouts, the clearance the drone kept, and physics steps per second
    (wall clock of ``advance`` only)."""
    frame_s = 1.0 / 30.0
    out = {
        "flown": 0,
        "collisions": 0,
        "arrived": 0,
        "timeouts": 0,
        "refused": 0,
        "min_clearance_m": np.inf,
        "steps": 0,
        "advance_s": 0.0,
        "advance_cpu_s": 0.0,
        "incidents": [],
    }
    for start, goal, duration_s in tqdm(pairs, desc=f"fly {name}", unit="route"):
        sim = DroneSimulator(config, flight_map)
        try:
            sim.spawn(start)
            sim.command_goto(goal)
        except DroneSimError as exc:
            out["refused"] += 1
            out["incidents"].append(
                {"start": start.tolist(), "goal": goal.tolist(), "what": f"refused: {exc}"}
            )
            continue
        out["flown"] += 1
        budget = 2.0 * duration_s + 5.0
        arrived = False
        while sim.time_s < budget and not arrived:
            t0, c0, before = time.perf_counter(), time.process_time(), sim.time_s
            events = sim.advance(frame_s)
            out["advance_s"] += time.perf_counter() - t0
            out["advance_cpu_s"] += time.process_time() - c0
            out["steps"] += round((sim.time_s - before) * config.physics_hz)
            out["min_clearance_m"] = min(out["min_clearance_m"], sim.status().clearance)
            for event in events:
                if event.kind == DroneEventKind.COLLISION:
                    out["collisions"] += 1
                    out["incidents"].append(
                        {
                            "start": start.tolist(),
                            "goal": goal.tolist(),
                            "what": f"t={event.time_s:.2f} s: {event.message}",
                        }
                    )
                arrived |= event.kind == DroneEventKind.ARRIVED
        out["arrived"] += arrived
        out["timeouts"] += not arrived
        if not arrived:
            out["incidents"].append(
                {"start": start.tolist(), "goal": goal.tolist(), "what": "did not arrive in time"}
            )
    out["steps_per_s"] = out["steps"] / max(out["advance_s"], 1e-9)
    out["steps_per_cpu_s"] = out["steps"] / max(out["advance_cpu_s"], 1e-9)
    out["realtime_factor"] = out["steps_per_cpu_s"] / config.physics_hz
    return out


# --- results -------------------------------------------------------------------------------
def summarise(
    flight_map: FlightMap, fused: dict, starts, goals, connected, results, flights: dict | None
) -> dict:
    ok = np.array([r["route"] is not None for r in results])
    ms = np.array([r["cpu_ms"] for r in results])  # one core's time: fair on a shared machine
    wall = np.array([r["ms"] for r in results])
    straight = np.linalg.norm(goals - starts, axis=1)
    lengths = np.array([r["route"].length_m if r["route"] else np.nan for r in results])
    ratio = (lengths / straight)[ok]
    reasons: dict[str, int] = {}
    for r in results:
        if r["reason"]:
            reasons[r["reason"]] = reasons.get(r["reason"], 0) + 1
    extent = np.array(flight_map.shape) * flight_map.voxel_m
    summary = {
        "frames_fused": fused["frames_fused"],
        "map_m": [round(float(x), 2) for x in extent],
        "grid": list(flight_map.shape),
        "free_fraction": float(np.mean(flight_map.esdf > 0)),
        "esdf_full_ms": fused["esdf_full_ms"],
        "esdf_incremental_ms": fused["esdf_incremental_ms"],
        "pairs": len(results),
        "connected_pairs": int(connected.sum()),
        "success": 100.0 * ok.mean(),
        "success_connected": 100.0 * ok[connected].mean() if connected.any() else float("nan"),
        "unreachable_ok": int((~ok & ~connected).sum()),
        "failures": reasons,
        "straight_m_median": float(np.median(straight)),
        "plan_ms_first": float(ms[0]),
        "plan_ms_p50": float(np.percentile(ms[1:], 50)),
        "plan_ms_p95": float(np.percentile(ms[1:], 95)),
        "plan_ms_max": float(ms[1:].max()),
        "plan_ms_p95_found": float(np.percentile(ms[1:][ok[1:]], 95)),
        "plan_wall_ms_p50": float(np.percentile(wall[1:], 50)),
        "plan_wall_ms_p95": float(np.percentile(wall[1:], 95)),
        "failed_pairs": [
            {k: r[k] for k in ("start", "goal", "reason")} | {"connected": bool(c)}
            for r, c in zip(results, connected, strict=True)
            if r["reason"]
        ],
        "length_ratio_median": float(np.median(ratio)),
        "length_ratio_p95": float(np.percentile(ratio, 95)),
    }
    if flights is not None:
        summary.update({k: (float(v) if isinstance(v, float) else v) for k, v in flights.items()})
    return summary


ROWS = (  # (key, label, format)
    ("map_m", "map extent (m)", lambda v: " x ".join(f"{x:.1f}" for x in v)),
    ("frames_fused", "frames fused", str),
    ("free_fraction", "free cells", "{:.0%}".format),
    ("esdf_full_ms", "ESDF full build (CPU ms)", "{:.0f}".format),
    ("esdf_incremental_ms", "ESDF update, +1 frame (CPU ms)", "{:.0f}".format),
    ("pairs", "start/goal pairs", str),
    ("connected_pairs", "  connected in the 5 cm grid", str),
    ("success", "success, all pairs (%)", "{:.1f}".format),
    ("success_connected", "success, connected pairs (%)", "{:.1f}".format),
    ("unreachable_ok", "unreachable, not connected", str),
    ("plan_ms_first", "first plan, builds lattice (CPU ms)", "{:.1f}".format),
    ("plan_ms_p50", "planning p50 (CPU ms)", "{:.1f}".format),
    ("plan_ms_p95", "planning p95 (CPU ms)", "{:.1f}".format),
    ("plan_ms_max", "planning max (CPU ms)", "{:.1f}".format),
    ("plan_wall_ms_p50", "planning p50 (wall ms, shared machine)", "{:.1f}".format),
    ("plan_wall_ms_p95", "planning p95 (wall ms, shared machine)", "{:.1f}".format),
    ("straight_m_median", "straight line, median (m)", "{:.2f}".format),
    ("length_ratio_median", "length / straight, median", "{:.3f}".format),
    ("length_ratio_p95", "length / straight, p95", "{:.3f}".format),
    ("flown", "routes flown", str),
    ("arrived", "  arrived", str),
    ("collisions", "  collisions", str),
    ("min_clearance_m", "  least clearance in flight (m)", "{:.3f}".format),
    ("steps_per_cpu_s", "physics steps / CPU s", "{:,.0f}".format),
    ("steps_per_s", "physics steps / wall s", "{:,.0f}".format),
    ("realtime_factor", "physics x real time (CPU)", "{:.0f}x".format),
)


def cell(summary: dict, key: str, fmt) -> str:
    if key not in summary:
        return "-"
    text = fmt(summary[key])
    if key in TARGETS:
        text += " ✓" if TARGETS[key][1](summary[key]) else " ✗"
    return text


def tables(summaries: dict[str, dict], config: SimulationConfig) -> tuple[Table, str]:
    table = Table(
        title=f"Route planning in fused maps (drone radius {config.radius_m:g} m + "
        f"{config.planning_margin_m:g} m margin)"
    )
    table.add_column("figure")
    for name in summaries:
        table.add_column(name, justify="right")
    table.add_column("target")
    lines = [
        "| figure | " + " | ".join(summaries) + " | target |",
        "|---" * (len(summaries) + 2) + "|",
    ]
    for key, label, fmt in ROWS:
        cells = [cell(s, key, fmt) for s in summaries.values()]
        target = TARGETS.get(key, ("",))[0]
        table.add_row(label, *cells, target)
        lines.append(f"| {label.strip()} | " + " | ".join(cells) + f" | {target} |")
    return table, "\n".join(lines) + "\n"


def plot_routes(
    path: Path,
    flight_map: FlightMap,
    occupied: np.ndarray,
    clearance_m: float,
    routes: list,
    title: str,
) -> None:
    """Top view: occupied cells within the heights the drone can fly at (darker = more of them
    in the column; floor and ceiling lie outside that band), columns with flyable space light
    blue, a few routes (circle: start, square: goal)."""
    flyable = flight_map.esdf >= clearance_m
    heights = np.flatnonzero(flyable.any(axis=(0, 1)))
    band = slice(heights.min(), heights.max() + 1) if heights.size else slice(0, 0)
    obstacles = occupied[:, :, band].sum(axis=2).astype(float)
    lo, hi = flight_map.bounds.lo, flight_map.bounds.hi
    extent = (lo[0], hi[0], lo[1], hi[1])
    fig, ax = plt.subplots(figsize=(8, 8), dpi=110)
    ax.imshow(
        np.where(flyable.any(axis=2), 1.0, np.nan).T,
        origin="lower",
        extent=extent,
        cmap="Blues",
        vmin=0,
        vmax=5,
    )
    ax.imshow(
        np.where(obstacles > 0, obstacles, np.nan).T,
        origin="lower",
        extent=extent,
        cmap="Greys",
        vmin=0,
        vmax=max(obstacles.max(), 1),
    )
    colours = plt.cm.tab10(np.arange(len(routes)) % 10)
    for route, colour in zip(routes, colours, strict=True):
        ax.plot(route.path[:, 0], route.path[:, 1], "-", color=colour, lw=2)
        ax.plot(*route.path[0, :2], "o", color=colour, ms=6)
        ax.plot(*route.path[-1, :2], "s", color=colour, ms=6)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_aspect("equal")
    ax.set_title(title)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def benchmark(path: Path, args, config: SimulationConfig) -> dict:
    """Fuse, plan, fly and picture one sequence; returns its figures."""
    fused = fuse_flight_map(path, args.every, config.voxel_m, config)
    flight_map = fused["flight_map"]
    rng = np.random.default_rng(args.seed)
    clearance = config.planning_radius_m + 1e-6
    points = flight_map.random_free_points(2 * args.pairs, clearance, rng)
    starts, goals = points[: args.pairs], points[args.pairs :]
    connected = connected_in_grid(flight_map, clearance, starts, goals)
    results = plan_pairs(flight_map, starts, goals, config, path.name)
    flown = [
        (s, g, r["route"].duration_s)
        for s, g, r in zip(starts, goals, results, strict=True)
        if r["route"] is not None
    ][: args.fly]
    flights = fly_routes(flight_map, flown, config, path.name) if flown else None
    summary = summarise(flight_map, fused, starts, goals, connected, results, flights)
    routes = [r["route"] for r in results if r["route"] is not None]
    picks = sorted(routes[:40], key=lambda r: -r.length_m)[:8]
    plot_routes(
        args.out / f"planning_{path.name}.png",
        flight_map,
        fused["occupied"],
        clearance,
        picks,
        f"{path.name}: flight map from above, {len(picks)} routes",
    )
    return summary


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "sequences",
        nargs="*",
        type=Path,
        help=f"TUM-layout folders (default: {', '.join(SEQUENCES)} in {DATA})",
    )
    parser.add_argument("--pairs", type=int, default=1000, help="start/goal pairs per sequence")
    parser.add_argument("--fly", type=int, default=1000, help="fly at most this many routes")
    parser.add_argument("--every", type=int, default=5, help="fuse every n-th frame")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=REPO_ROOT / "benchmarks" / "results")
    args = parser.parse_args(argv)
    config = SimulationConfig()
    sequences = args.sequences or [DATA / name for name in SEQUENCES]
    header = {
        "date": datetime.datetime.now().isoformat(timespec="seconds"),
        "machine": platform.platform(),
        "cpu_count": os.cpu_count(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "command": shlex.join(["python", "benchmarks/planning.py", *argv]),
    }
    summaries, failed = {}, 0
    args.out.mkdir(parents=True, exist_ok=True)
    for path in sequences:
        try:
            summary = benchmark(path, args, config)
        except DroneSimError as exc:
            console.print(f"[red]{path.name}: skipped: {exc}[/]")
            failed += 1
            continue
        summaries[path.name] = summary
    if not summaries:
        return 1
    table, markdown = tables(summaries, config)
    console.print(table)
    with open(args.out / "planning.md", "a") as md:
        md.write(
            f"\n## Run {header['date']}\n\n- machine: {header['machine']}, "
            f"{header['cpu_count']} CPUs, numpy on 1 thread; python {header['python']}, "
            f"numpy {header['numpy']}\n- drone: radius {config.radius_m:g} m, planning margin "
            f"{config.planning_margin_m:g} m\n- command: `{header['command']}`\n\n{markdown}"
        )
    json_path = args.out / "planning.json"
    stored = json.loads(json_path.read_text()) if json_path.is_file() else {}
    for name, summary in summaries.items():
        stored[name] = {"header": header, **summary}
    json_path.write_text(json.dumps(stored, indent=1) + "\n")
    console.print(f"results: {args.out / 'planning.md'}, {json_path}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
