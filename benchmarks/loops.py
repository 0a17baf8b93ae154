"""Loop closure benchmark (issue 15, item 2): sequences that come back to where they started.

Each case plays the first N frames of a sequence forward, then back to its first frame
(``server.datasets.there_and_back``), and tracks it twice, as ``track`` does: loop closure off
(odometry), then on (``registration.loops.enabled``: keyframe look-up, verification, pose graph,
every frame moved with its keyframe). Prints per case the keyframes, the loops found, the ATE of
the odometry and of the corrected trajectory, and what loop closure cost in CPU time (each
keyframe's look-up, verification and refinement; the graph's optimisation), with the targets
beside them, and how far the graph's odometry and loop edges are from the ground truth's
relative poses (medians: a loop edge less accurate than the odometry's yet trusted as much
makes the correction worse); appends to <out>/loops.md, writes
<out>/loops.json and a top view per case.

    python benchmarks/loops.py                           # ~3 min on 2 cores
    python benchmarks/loops.py --case synthetic_room0:120 --case 7scenes_a:200

Targets: at least one loop found on every case; the corrected ATE no worse than the odometry's
(within 2 %: what one run's noise can move it by).
"""

from __future__ import annotations

import os

# One thread everywhere, as the registration benchmark, set before numpy/OpenCV/Open3D start.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import datetime  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import shlex  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import numpy as np  # noqa: E402
from rich.console import Console  # noqa: E402
from rich.table import Table  # noqa: E402

REPO_ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO_ROOT))
sys.path.insert(0, str(REPO_ROOT / "benchmarks"))

from registration import git_commit, plot_topview  # noqa: E402

import server.pipeline  # noqa: E402
from server.datasets import open_dataset  # noqa: E402
from server.datasets.there_and_back import ThereAndBack  # noqa: E402
from server.geometry import invert, rotation_angle_deg  # noqa: E402
from server.pipeline import run_odometry  # noqa: E402
from server.registration.config import RegistrationConfig  # noqa: E402
from server.registration.loops import LoopCloser  # noqa: E402

console = Console(width=150)


class TimedLoopCloser(LoopCloser):
    """The pipeline's loop closer, with the CPU time (this thread's: what a busy machine does
    not inflate) of each keyframe's look-up and of the graph's optimisation recorded."""

    add_ms: list[float] = []
    optimise_ms: list[float] = []
    last: LoopCloser | None = None  # the latest run's, for its edges

    def add_keyframe(self, *args, **kwargs):
        TimedLoopCloser.last = self
        t0 = time.thread_time()
        try:
            return super().add_keyframe(*args, **kwargs)
        finally:
            TimedLoopCloser.add_ms.append(1e3 * (time.thread_time() - t0))

    def optimise(self, *args, **kwargs):
        t0 = time.thread_time()
        try:
            return super().optimise(*args, **kwargs)
        finally:
            TimedLoopCloser.optimise_ms.append(1e3 * (time.thread_time() - t0))


server.pipeline.LoopCloser = TimedLoopCloser  # type: ignore[misc]
DATA = REPO_ROOT.parent / "shared" / "data"
DEFAULT_CASES = ["synthetic_room0:100", "synthetic_room0:150", "7scenes_a:200", "7scenes_a:300"]
ATE_SLACK = 1.02  # corrected ATE within 2 % of the odometry's counts as no worse


def run_case(sequence: str, n: int, cfg: RegistrationConfig, out: Path, once: bool = False) -> dict:
    """Track the there-and-back case (``once``: the first n frames forward only) without and
    with loop closure; figures and a top view."""
    path = Path(sequence) if Path(sequence).exists() else DATA / sequence
    ds = open_dataset(path) if once else ThereAndBack(open_dataset(path), n)
    frames = n if once else None
    odometry = run_odometry(
        ds, cfg.with_overrides(loops={"enabled": False}), max_frames=frames, progress=False
    )
    TimedLoopCloser.add_ms.clear()
    TimedLoopCloser.optimise_ms.clear()
    closed = run_odometry(
        ds, cfg.with_overrides(loops={"enabled": True}), max_frames=frames, progress=False
    )
    keyframes = len(closed.room.keyframes)
    loops = closed.summary["loops"]
    assert odometry.metrics is not None and closed.metrics is not None  # ground truth: checked
    row = {
        "case": f"{path.name} {'once' if once else 'there and back'} {n}",
        "frames": len(closed.trajectory),
        "keyframes": keyframes,
        "loops": loops["found"],
        "edges": loops["edges"],
        "ate_odometry_cm": 100 * odometry.metrics["ate_rmse_m"],
        "ate_corrected_cm": 100 * closed.metrics["ate_rmse_m"],
        "lookup_ms_median": float(np.median(TimedLoopCloser.add_ms)),
        "lookup_ms_max": float(np.max(TimedLoopCloser.add_ms)),
        "optimise_ms": float(sum(TimedLoopCloser.optimise_ms)),
    }
    assert TimedLoopCloser.last is not None
    row.update(edge_errors(ds, closed, TimedLoopCloser.last))
    row["loop_found_ok"] = row["loops"] >= 1
    row["ate_ok"] = row["ate_corrected_cm"] <= ATE_SLACK * row["ate_odometry_cm"]
    picture = out / f"loops_{path.name}_{n}{'_once' if once else ''}.png"
    plot_case(picture, row["case"], ds, odometry, closed)
    row["picture"] = picture.name
    return row


def edge_errors(ds, run, closer: LoopCloser) -> dict:
    """How far the graph's edges are from the ground truth's relative poses (cm, deg; medians):
    odometry edges (consecutive keyframes as tracked) and loop edges (as verified and refined).
    A loop edge much worse than the odometry's, trusted as much, makes the correction worse."""
    frame_of = {kf.id: kf.frame_index for kf in run.room.keyframes}
    gt = ds.ground_truth

    def truth(kf_id: int) -> np.ndarray:
        t = ds.timestamps[frame_of[kf_id]]
        return gt.poses[int(np.argmin(np.abs(gt.timestamps - t)))]

    errors: dict[bool, list[tuple[float, float]]] = {False: [], True: []}
    for old, new, T_old_new, loop in closer.edges():
        D = invert(invert(truth(old)) @ truth(new)) @ T_old_new
        errors[loop].append((100 * float(np.linalg.norm(D[:3, 3])), rotation_angle_deg(D)))
    out = {}
    for loop, name in ((False, "odometry"), (True, "loop")):
        e = np.array(errors[loop]).reshape(-1, 2)
        out[f"{name}_edge_cm"] = float(np.median(e[:, 0])) if len(e) else float("nan")
        out[f"{name}_edge_deg"] = float(np.median(e[:, 1])) if len(e) else float("nan")
    return out


def plot_case(path: Path, title: str, ds, odometry, closed) -> None:
    """Top view of truth, odometry and the corrected trajectory (registration.plot_topview)."""
    runs = {"odometry": odometry, "loops closed": closed}
    plot_topview(
        path,
        title,
        ds.ground_truth.poses[: len(closed.trajectory)],
        {name: run.trajectory.poses for name, run in runs.items()},
        {name: f"{name} ({100 * run.metrics['ate_rmse_m']:.2f} cm)" for name, run in runs.items()},
    )


def edges_text(r: dict) -> str:
    return (
        f"{r['odometry_edge_cm']:.2f} cm {r['odometry_edge_deg']:.2f}° / "
        f"{r['loop_edge_cm']:.2f} cm {r['loop_edge_deg']:.2f}°"
    )


def mark(ok: bool) -> str:
    return "✓" if ok else "✗"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--case",
        action="append",
        help="SEQUENCE:N (a folder, or a name under ../shared/data; played there and back, "
        "or with SEQUENCE:N:once its first N frames forward only), repeatable; "
        f"default: {' '.join(DEFAULT_CASES)}",
    )
    parser.add_argument("--out", type=Path, default=REPO_ROOT / "benchmarks" / "results")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    cfg = RegistrationConfig()
    rows = []
    for case in args.case or DEFAULT_CASES:
        once = case.endswith(":once")
        sequence, _, n = case.removesuffix(":once").rpartition(":")
        console.print(f"[bold]{sequence}[/] {'once' if once else 'there and back'}, {n} frames…")
        rows.append(run_case(sequence, int(n), cfg, args.out, once))

    table = Table(title="Loop closure on sequences that come back to their start")
    for col in ("case", "keyframes", "loops (>= 1)", "ATE odometry", "ATE corrected (<= odo)"):
        table.add_column(col)
    table.add_column("edge error, odometry / loop (cm, deg)")
    table.add_column("look-up ms (median / max)")
    table.add_column("optimise ms")
    lines = [
        "| case | keyframes | loops (>= 1) | ATE odometry [cm] | ATE corrected [cm] (<= odometry) "
        "| edge error against the truth, median: odometry / loop | look-up CPU ms per keyframe, "
        "median / max | optimise CPU ms | picture |",
        "|---|---:|---:|---:|---:|---|---:|---:|---|",
    ]
    for r in rows:
        table.add_row(
            r["case"],
            str(r["keyframes"]),
            f"{r['loops']} {mark(r['loop_found_ok'])}",
            f"{r['ate_odometry_cm']:.3f}",
            f"{r['ate_corrected_cm']:.3f} {mark(r['ate_ok'])}",
            edges_text(r),
            f"{r['lookup_ms_median']:.0f} / {r['lookup_ms_max']:.0f}",
            f"{r['optimise_ms']:.0f}",
        )
        lines.append(
            f"| {r['case']} | {r['keyframes']} | {r['loops']} {mark(r['loop_found_ok'])} "
            f"| {r['ate_odometry_cm']:.3f} | {r['ate_corrected_cm']:.3f} {mark(r['ate_ok'])} "
            f"| {edges_text(r)} | {r['lookup_ms_median']:.0f} / {r['lookup_ms_max']:.0f} "
            f"| {r['optimise_ms']:.0f} "
            f"| `{r['picture']}` |"
        )
    console.print(table)
    header = (
        f"\n## Run {datetime.datetime.now().isoformat(timespec='seconds')}\n\n"
        f"- commit: {git_commit()}\n"
        f"- machine: {platform.platform()}, {os.cpu_count()} CPUs, 1 thread\n"
        f"- command: `python benchmarks/loops.py {shlex.join(argv or sys.argv[1:])}`\n\n"
    )
    with open(args.out / "loops.md", "a") as f:
        f.write(header + "\n".join(lines) + "\n")
    (args.out / "loops.json").write_text(json.dumps(rows, indent=1))
    return 0 if all(r["loop_found_ok"] and r["ate_ok"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
