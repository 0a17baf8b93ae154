"""Mapper CPU per fused frame, before and after a change, and whether the map stayed as good.

A session's mapper process (server/sessions/processes/mapper.py ``Mapper``) as a live session
drives it, in one process on one thread (``time.process_time``): every ``--every``-th frame of a
real sequence fused at its ground-truth pose (``mapping.fuse_every``), the drone's occupancy
asked for with every ``--occupancy-every``-th fusion (``flight_map_interval_s`` 3 s at 15 fps
and fuse_every 3: every 15th), a snapshot (``Mapper.save``: map.npz and map.ply) after every
``--snapshot-every``-th (``snapshot_interval_s`` 10 s: every 50th), and the frame unpickled as it
arrives over the mapper's pipe. CPU per fused frame, stage by stage: receive, integrate (Open3D
and the blocks it is given), preview, occupancy, snapshot, the rest of ``fuse``.

Each setting runs in a process of its own (``--repeats`` times, settings alternated so that they
share the machine's load; the least CPU of the repeats counts): ``before`` is the code of
``--base`` (a checkout of the last commit, e.g. ``git archive HEAD | tar -x -C /tmp/base``) at
its defaults, or without ``--base`` this tree with ``--before`` settings; ``after`` this tree at
its defaults; ``--variant LABEL:KEY=VALUE,...`` adds settings of this tree (keys of the mapping
section, e.g. ``tsdf.block_search_width_px=0``).

The map's quality, per setting, from its last map (Open3D on one thread is deterministic):

- accuracy: median distance of the map's surface points (``point_cloud``) to the measured
  surface (every fused frame's depth back-projected at its ground-truth pose, every 4th pixel);
- completeness: the share of measured points within 3 cm of a surface point;
- against ``before``'s map: the drone's occupancy (``TSDFMap.occupancy``, 5 cm cells in a
  gravity-aligned frame, as the session's flight map): IoU of the occupied cells, of the free
  cells, and the share of cells either map knows that both call the same (unknown, free or
  occupied); and the median distance from this map's surface points to before's.
- ``floor``: before's settings on the frames in between (``--every`` offset by one): how much
  two maps of the same room at the same quality differ, for scale.

Targets: CPU per fused frame at most 0.7 of before's; accuracy and completeness within 5 % of
before's; against before's map at least 95 % of the cells in the same state and an occupied IoU
of at least 0.95 (the floor, for scale, is no target). Appends the tables to
``benchmarks/results/mapping_cpu.md``.

    git archive HEAD | tar -x -C /tmp/base      # the last commit's code, beside this tree
    python benchmarks/mapping_cpu.py --base /tmp/base                  # 7scenes_a + tum_fr1_xyz
    python benchmarks/mapping_cpu.py ../shared/data/7scenes_a --repeats 1 \
        --variant 'every pixel:tsdf.block_search_width_px=0'
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # one core: numpy must not fan out

import argparse  # noqa: E402
import json  # noqa: E402
import pickle  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

REPO_ROOT = Path(__file__).resolve().parents[1]
DATA = REPO_ROOT.parent / "shared" / "data"
RESULTS = REPO_ROOT / "benchmarks" / "results" / "mapping_cpu.md"
STAGES = ("receive", "integrate", "preview", "occupancy", "snapshot", "other")
CPU_TARGET = 0.7  # after / before, CPU per fused frame
QUALITY_SLACK = 0.05  # accuracy, completeness, agreement: at most 5 % worse
NEAR_M = 0.03  # completeness: a measured point within this of the map's surface
OCCUPANCY_CELL_M = 0.05  # SimulationConfig.voxel_m, the drone's flight map
# Before issue 34's settings, for a run without --base: blocks of 16^3 found from every pixel
# (the free space is carved into a grid of its own all the same, not into the TSDF as before).
BEFORE = ("tsdf.block_search_width_px=0", "tsdf.block_resolution=16", "tsdf.block_count=256")


# ---- one setting, in a process of its own ------------------------------------------------------


def load_frames(sequence: Path, start: int, every: int, frames: int):
    """(dataset, [(colour, depth, T_world_camera)]) of every ``every``-th frame from ``start``
    that has a ground-truth pose, at most ``frames``."""
    from server.datasets import open_dataset
    from server.pipeline import ground_truth_pose_at

    dataset = open_dataset(sequence)
    out = []
    for i in range(start, len(dataset), every):
        frame = dataset[i]
        T = ground_truth_pose_at(dataset, frame.timestamp)
        if T is not None:
            out.append((frame.colour, frame.depth, np.asarray(T, np.float64)))
        if len(out) == frames:
            break
    return dataset, out


def flight_frame(poses: list[np.ndarray]) -> np.ndarray:
    """R_flight_world: z up (the world axis nearest the cameras' up), as benchmarks/planning.py."""
    from server.evaluation.plots import top_view_basis, up_direction

    up = up_direction(np.array(poses))
    return np.vstack([top_view_basis(up), up])


def parse_settings(items: list[str]) -> tuple[dict, dict]:
    """KEY=VALUE items (mapping keys, ``tsdf.`` for the TSDF's) -> (mapping, tsdf) overrides."""
    mapping: dict = {}
    tsdf: dict = {}
    for item in items:
        key, _, text = item.partition("=")
        value = json.loads(text) if text not in ("true", "false") else text == "true"
        if key.startswith("tsdf."):
            tsdf[key[5:]] = value
        else:
            mapping[key] = value
    return mapping, tsdf


def child(args: argparse.Namespace) -> int:
    """Fuse the sequence with one setting; print one JSON line: CPU seconds per stage."""
    sys.path.insert(0, str(args.tree))
    import open3d as o3d

    o3d.utility.set_max_threads(1)
    from server.mapping.config import MappingConfig, TSDFConfig
    from server.sessions.processes.mapper import Mapper

    dataset, frames = load_frames(args.sequence, args.start, args.every, args.frames)
    K = dataset.intrinsics
    R = flight_frame([T for _, _, T in frames])
    mapping, tsdf = parse_settings(args.set)
    mapper = Mapper(MappingConfig(tsdf=TSDFConfig(**tsdf), **mapping))
    cpu = dict.fromkeys(STAGES, 0.0)

    def timed(stage: str, call):
        def wrapper(*a, **kw):
            start = time.process_time()
            try:
                return call(*a, **kw)
            finally:
                cpu[stage] += time.process_time() - start

        return wrapper

    # Instance attributes over the methods: Mapper.fuse calls these, in either tree.
    tsdf_map = mapper.map
    tsdf_map.integrate = timed("integrate", tsdf_map.integrate)  # type: ignore[method-assign]
    tsdf_map.occupancy_update = timed("occupancy", tsdf_map.occupancy_update)  # type: ignore[method-assign]
    mapper.preview.new_points = timed("preview", mapper.preview.new_points)  # type: ignore[method-assign]
    fuse_s = 0.0
    with tempfile.TemporaryDirectory() as snapshots:
        for n, (colour, depth, T) in enumerate(frames):
            wire = pickle.dumps((colour, depth, K, T), protocol=pickle.HIGHEST_PROTOCOL)
            start = time.process_time()
            colour, depth, K_in, T = pickle.loads(wire)
            cpu["receive"] += time.process_time() - start
            occupancy = (OCCUPANCY_CELL_M, R) if n % args.occupancy_every == 0 else None
            start = time.process_time()
            mapper.fuse(colour, depth, K_in, T, occupancy)
            fuse_s += time.process_time() - start
            if n % args.snapshot_every == args.snapshot_every - 1:
                start = time.process_time()
                mapper.save(snapshots)
                cpu["snapshot"] += time.process_time() - start
    cpu["other"] = fuse_s - cpu["integrate"] - cpu["preview"] - cpu["occupancy"]
    if args.map_out is not None:
        tsdf_map.save(args.map_out)
    stats = tsdf_map.stats()
    print(json.dumps({"cpu_s": cpu, "fused": len(frames), "blocks": stats["active_blocks"]}))
    return 0


# ---- the comparison -------------------------------------------------------------------------


def run_setting(
    args: argparse.Namespace,
    sequence: Path,
    tree: Path,
    settings: list[str],
    map_out: Path | None,
    start: int = 0,
) -> dict:
    command = [
        sys.executable,
        str(Path(__file__).resolve()),
        "--child",
        "--tree",
        str(tree),
        str(sequence),
        "--start",
        str(start),
        "--every",
        str(args.every),
        "--frames",
        str(args.frames),
        "--occupancy-every",
        str(args.occupancy_every),
        "--snapshot-every",
        str(args.snapshot_every),
    ]
    for item in settings:
        command += ["--set", item]
    if map_out is not None:
        command += ["--map-out", str(map_out)]
    # The tree's own server package: nothing of this checkout on the child's path first.
    env = {**os.environ, "PYTHONPATH": str(tree)}
    done = subprocess.run(command, capture_output=True, text=True, env=env, cwd=tree)
    if done.returncode != 0:
        raise SystemExit(f"{tree} {settings} failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def measured_surface(sequence: Path, start: int, every: int, frames: int, depth_max_m: float):
    from server.geometry import backproject

    dataset, loaded = load_frames(sequence, start, every, frames)
    clouds = []
    for _, depth, T in loaded:
        points, _ = backproject(np.where(depth <= depth_max_m, depth, 0), dataset.intrinsics, 4)
        clouds.append(points @ T[:3, :3].T + T[:3, 3])
    return np.concatenate(clouds), flight_frame([T for _, _, T in loaded])


def cell_states(grid) -> tuple[np.ndarray, np.ndarray]:
    """(cells (N, 3) int64, state (N,): 1 free, 2 occupied) of an occupancy grid's known cells."""
    origin, occupied, observed = grid
    lo = np.rint(np.asarray(origin) / OCCUPANCY_CELL_M).astype(np.int64)
    cells = np.argwhere(observed)
    return cells + lo, np.where(occupied[observed], 2, 1)


def agreement(grid, reference) -> dict:
    """Occupied IoU, free IoU and the share of cells known to either map with the same state."""
    from server.mapping.occupancy import pack_keys

    cells, state = cell_states(grid)
    ref_cells, ref_state = cell_states(reference)
    keys, ref_keys = pack_keys(cells), pack_keys(ref_cells)
    union = np.union1d(keys, ref_keys)
    a = np.zeros(len(union), np.int8)
    b = np.zeros(len(union), np.int8)
    a[np.searchsorted(union, keys)] = state
    b[np.searchsorted(union, ref_keys)] = ref_state

    def iou(s: int) -> float:
        either = (a == s) | (b == s)
        return float(((a == s) & (b == s)).sum() / max(either.sum(), 1))

    return {"occupied_iou": iou(2), "free_iou": iou(1), "agree": float((a == b).mean())}


def quality(map_path: Path, reference: Path, surface: np.ndarray, R: np.ndarray) -> dict:
    from scipy.spatial import cKDTree

    from server.mapping.tsdf import TSDFMap

    tsdf = TSDFMap.load(map_path)
    ref = TSDFMap.load(reference)
    points, _ = tsdf.point_cloud()
    ref_points, _ = ref.point_cloud()
    surface_tree = cKDTree(surface)
    accuracy = surface_tree.query(points, workers=1)[0]
    completeness = cKDTree(points).query(surface[::10], workers=1)[0] < NEAR_M
    to_ref = cKDTree(ref_points).query(points, workers=1)[0]
    grid = tsdf.occupancy(OCCUPANCY_CELL_M, R)
    return {
        "points": len(points),
        "accuracy_mm": 1e3 * float(np.median(accuracy)),
        "completeness": float(completeness.mean()),
        "to_before_mm": 1e3 * float(np.median(to_ref)),
        **agreement(grid, ref.occupancy(OCCUPANCY_CELL_M, R)),
    }


def compare(args: argparse.Namespace, sequence: Path, work: Path) -> tuple[list[str], bool]:
    """Run every setting on ``sequence``; the markdown lines of its tables and whether every
    target was met."""
    from rich.console import Console
    from rich.table import Table

    base = args.base.resolve() if args.base else REPO_ROOT
    settings: dict[str, tuple[Path, list[str]]] = {
        "before": (base, [] if args.base else list(args.before)),
        "after": (REPO_ROOT, []),
    }
    for variant in args.variant:
        label, _, items = variant.partition(":")
        settings[label] = (REPO_ROOT, [i for i in items.split(",") if i])
    runs: dict[str, list[dict]] = {label: [] for label in settings}
    for r in range(args.repeats):
        for label, (tree, items) in settings.items():
            map_out = work / f"{label}.npz" if r == 0 else None
            runs[label].append(run_setting(args, sequence, tree, items, map_out))
            total = sum(runs[label][-1]["cpu_s"].values())
            print(
                f"  {sequence.name} {label} run {r + 1}: {1e3 * total / args.frames:.1f} ms/frame"
            )
    floor_tree, floor_items = settings["before"]
    run_setting(args, sequence, floor_tree, floor_items, work / "floor.npz", start=1)

    best = {label: min(rs, key=lambda r: sum(r["cpu_s"].values())) for label, rs in runs.items()}
    surface, R = measured_surface(sequence, 0, args.every, args.frames, 4.0)
    reference = work / "before.npz"
    figures = {label: quality(work / f"{label}.npz", reference, surface, R) for label in runs}
    figures["floor"] = quality(work / "floor.npz", reference, surface, R)

    before_cpu = sum(best["before"]["cpu_s"].values())
    fused = best["before"]["fused"]
    columns = ["setting", *[f"{s} ms" for s in STAGES], "total ms", "x before", "blocks"]
    cpu_rows = []
    for label, run in best.items():
        total = sum(run["cpu_s"].values())
        cpu_rows.append(
            [
                label,
                *[f"{1e3 * run['cpu_s'][s] / run['fused']:.1f}" for s in STAGES],
                f"**{1e3 * total / run['fused']:.1f}**",
                f"{total / before_cpu:.2f}",
                str(run["blocks"]),
            ]
        )
    ref_q = figures["before"]
    after_q, after_cpu = figures["after"], sum(best["after"]["cpu_s"].values())
    checks = {
        f"CPU per fused frame <= {CPU_TARGET} x before": after_cpu <= CPU_TARGET * before_cpu,
        "accuracy within 5 % of before's": after_q["accuracy_mm"]
        <= (1 + QUALITY_SLACK) * ref_q["accuracy_mm"],
        "completeness within 5 % of before's": after_q["completeness"]
        >= (1 - QUALITY_SLACK) * ref_q["completeness"],
        "occupancy: >= 95 % of the cells as before's": after_q["agree"] >= 1 - QUALITY_SLACK,
        "occupied IoU with before's >= 0.95": after_q["occupied_iou"] >= 1 - QUALITY_SLACK,
    }
    q_columns = [
        "map",
        "surface points",
        "accuracy mm",
        "completeness",
        "to before mm",
        "occupied IoU",
        "free IoU",
        "agree",
    ]
    q_rows = [
        [
            label,
            str(q["points"]),
            f"{q['accuracy_mm']:.2f}",
            f"{q['completeness']:.3f}",
            f"{q['to_before_mm']:.2f}",
            f"{q['occupied_iou']:.3f}",
            f"{q['free_iou']:.3f}",
            f"{q['agree']:.3f}",
        ]
        for label, q in figures.items()
    ]
    console = Console(width=max(Console().width, 140))
    title = (
        f"{sequence.name}: {fused} fused frames (1 in {args.every}), CPU ms per fused frame, "
        f"least of {args.repeats}, one thread"
    )
    for cols, rows, head in ((columns, cpu_rows, title), (q_columns, q_rows, "map quality")):
        table = Table(title=head)
        for c in cols:
            table.add_column(c, justify="left" if c in ("setting", "map") else "right")
        for row in rows:
            table.add_row(*[c.replace("**", "") for c in row])
        console.print(table)
    for name, ok in checks.items():
        console.print(f"  {'✓' if ok else '✗'} {name}")
    settings_line = "; ".join(
        f"{label}: {'base ' if tree != REPO_ROOT else ''}{', '.join(items) or 'defaults'}"
        for label, (tree, items) in settings.items()
    )
    lines = [
        f"\n### {title}\n",
        f"Settings: {settings_line}.\n",
        f"| {' | '.join(columns)} |",
        "|---|" + "--:|" * (len(columns) - 1),
        *[f"| {' | '.join(row)} |" for row in cpu_rows],
        "",
        f"| {' | '.join(q_columns)} |",
        "|---|" + "--:|" * (len(q_columns) - 1),
        *[f"| {' | '.join(row)} |" for row in q_rows],
        "",
        *[f"- {'✓' if ok else '✗'} {name}" for name, ok in checks.items()],
    ]
    return lines, all(checks.values())


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument(
        "sequences", nargs="*", type=Path, default=[DATA / "7scenes_a", DATA / "tum_fr1_xyz"]
    )
    parser.add_argument("--base", type=Path, help="a checkout of the code before the change")
    parser.add_argument("--before", nargs="*", default=list(BEFORE), help="without --base")
    parser.add_argument("--variant", action="append", default=[], help="LABEL:KEY=V,KEY=V")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--every", type=int, default=3, help="fuse every n-th frame")
    parser.add_argument("--frames", type=int, default=200, help="fused frames")
    parser.add_argument("--occupancy-every", type=int, default=15)
    parser.add_argument("--snapshot-every", type=int, default=50)
    parser.add_argument("--no-record", action="store_true", help="do not append to results")
    # The child's own arguments.
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--tree", type=Path, default=REPO_ROOT, help=argparse.SUPPRESS)
    parser.add_argument("--start", type=int, default=0, help=argparse.SUPPRESS)
    parser.add_argument("--set", action="append", default=[], help=argparse.SUPPRESS)
    parser.add_argument("--map-out", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        (args.sequence,) = args.sequences
        return child(args)

    sys.path.insert(0, str(REPO_ROOT))
    from benchmarks.provenance import run_heading, utc_stamp

    stamp = utc_stamp()
    lines: list[str] = []
    met = True
    for sequence in [s.resolve() for s in args.sequences]:
        with tempfile.TemporaryDirectory() as work:
            seq_lines, seq_met = compare(args, sequence, Path(work))
        lines += seq_lines
        met = met and seq_met
    if not args.no_record:
        note = f"; base: {args.base}" if args.base else ""
        RESULTS.parent.mkdir(parents=True, exist_ok=True)
        with RESULTS.open("a") as out:
            if out.tell() == 0:
                out.write(
                    "# Mapper CPU per fused frame (`benchmarks/mapping_cpu.py`), newest last\n"
                )
            out.write("\n".join(run_heading(stamp, note) + lines) + "\n")
        print(f"appended to {RESULTS}")
    return 0 if met else 1


if __name__ == "__main__":
    raise SystemExit(main())
