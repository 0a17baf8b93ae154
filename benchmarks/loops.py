"""Loop closure benchmark (issue 15, item 2): sequences that come back to where they started.

Each case plays the first N frames of a sequence forward, then back to its first frame
(``server.datasets.there_and_back``), and tracks it twice, as ``track`` does: loop closure off
(odometry), then on (``registration.loops.enabled``: keyframe look-up, verification, pose graph,
every frame moved with its keyframe). Prints per case the keyframes, the loops found, the ATE of
the odometry and of the corrected trajectory, and what loop closure cost in CPU time (each
keyframe's look-up, verification and refinement; the graph's optimisation), with the targets
beside them; appends to <out>/loops.md, writes
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
from server.pipeline import run_odometry  # noqa: E402
from server.registration.config import RegistrationConfig  # noqa: E402
from server.registration.loops import LoopCloser  # noqa: E402

console = Console(width=150)


class TimedLoopCloser(LoopCloser):
    """The pipeline's loop closer, with the CPU time (this thread's: what a busy machine does
    not inflate) of each keyframe's look-up and of the graph's optimisation recorded."""

    add_ms: list[float] = []
    optimise_ms: list[float] = []

    def add_keyframe(self, *args, **kwargs):
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


def run_case(sequence: str, n: int, cfg: RegistrationConfig, out: Path) -> dict:
    """Track the there-and-back case without and with loop closure; figures and a top view."""
    path = Path(sequence) if Path(sequence).exists() else DATA / sequence
    ds = ThereAndBack(open_dataset(path), n)
    odometry = run_odometry(ds, cfg.with_overrides(loops={"enabled": False}), progress=False)
    TimedLoopCloser.add_ms.clear()
    TimedLoopCloser.optimise_ms.clear()
    closed = run_odometry(ds, cfg.with_overrides(loops={"enabled": True}), progress=False)
    keyframes = len(closed.room.keyframes)
    loops = closed.summary["loops"]
    assert odometry.metrics is not None and closed.metrics is not None  # ground truth: checked
    row = {
        "case": f"{path.name} there and back {n}",
        "frames": len(ds),
        "keyframes": keyframes,
        "loops": loops["found"],
        "edges": loops["edges"],
        "ate_odometry_cm": 100 * odometry.metrics["ate_rmse_m"],
        "ate_corrected_cm": 100 * closed.metrics["ate_rmse_m"],
        "lookup_ms_median": float(np.median(TimedLoopCloser.add_ms)),
        "lookup_ms_max": float(np.max(TimedLoopCloser.add_ms)),
        "optimise_ms": float(sum(TimedLoopCloser.optimise_ms)),
    }
    row["loop_found_ok"] = row["loops"] >= 1
    row["ate_ok"] = row["ate_corrected_cm"] <= ATE_SLACK * row["ate_odometry_cm"]
    picture = out / f"loops_{path.name}_{n}.png"
    plot_case(picture, row["case"], ds, odometry, closed)
    row["picture"] = picture.name
    return row


def plot_case(path: Path, title: str, ds, odometry, closed) -> None:
    """Top view of truth, odometry and the corrected trajectory (registration.plot_topview)."""
    runs = {"odometry": odometry, "loops closed": closed}
    plot_topview(
        path,
        title,
        ds.ground_truth.poses,
        {name: run.trajectory.poses for name, run in runs.items()},
        {name: f"{name} ({100 * run.metrics['ate_rmse_m']:.2f} cm)" for name, run in runs.items()},
    )


def mark(ok: bool) -> str:
    return "✓" if ok else "✗"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--case",
        action="append",
        help="SEQUENCE:N (a folder, or a name under ../shared/data), repeatable; "
        f"default: {' '.join(DEFAULT_CASES)}",
    )
    parser.add_argument("--out", type=Path, default=REPO_ROOT / "benchmarks" / "results")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    cfg = RegistrationConfig()
    rows = []
    for case in args.case or DEFAULT_CASES:
        sequence, _, n = case.rpartition(":")
        console.print(f"[bold]{sequence}[/] there and back, {n} frames…")
        rows.append(run_case(sequence, int(n), cfg, args.out))

    table = Table(title="Loop closure on sequences that come back to their start")
    for col in ("case", "keyframes", "loops (>= 1)", "ATE odometry", "ATE corrected (<= odo)"):
        table.add_column(col)
    table.add_column("look-up ms (median / max)")
    table.add_column("optimise ms")
    lines = [
        "| case | keyframes | loops (>= 1) | ATE odometry [cm] | ATE corrected [cm] (<= odometry) "
        "| look-up CPU ms per keyframe, median / max | optimise CPU ms | picture |",
        "|---|---:|---:|---:|---:|---:|---:|---|",
    ]
    for r in rows:
        table.add_row(
            r["case"],
            str(r["keyframes"]),
            f"{r['loops']} {mark(r['loop_found_ok'])}",
            f"{r['ate_odometry_cm']:.3f}",
            f"{r['ate_corrected_cm']:.3f} {mark(r['ate_ok'])}",
            f"{r['lookup_ms_median']:.0f} / {r['lookup_ms_max']:.0f}",
            f"{r['optimise_ms']:.0f}",
        )
        lines.append(
            f"| {r['case']} | {r['keyframes']} | {r['loops']} {mark(r['loop_found_ok'])} "
            f"| {r['ate_odometry_cm']:.3f} | {r['ate_corrected_cm']:.3f} {mark(r['ate_ok'])} "
            f"| {r['lookup_ms_median']:.0f} / {r['lookup_ms_max']:.0f} | {r['optimise_ms']:.0f} "
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
