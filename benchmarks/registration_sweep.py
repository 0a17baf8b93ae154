"""Our tracker (sparse + dense, the shipped defaults) over one sequence with several
configuration changes, the sequence loaded once: a quick search for what lowers the drift,
before a change is measured in full by ``benchmarks/registration.py``.

Each run starts from the ground-truth first pose and tracks every frame as ``track`` does
(colour resampled onto depth where frames come in, keyframes updated after each pose); the
first row is always the defaults, the baseline of the same sitting.

    python benchmarks/registration_sweep.py ../shared/data/7scenes_a \\
        --set solver.dense_weight=0.5 --set solver.photometric_weight=0.1 \\
        --set "depth.colour_focal_scale=0.9 depth.colour_offset_u_px=8"

Each ``--set`` is one run (several changes in one run: space-separated, quoted). Prints ATE
RMSE, RPE per second, the rotation gain over 5 frames (``metrics.rotation_gain``: the estimate's
slope on the ground truth / the ground truth's on the estimate; both 1 when it turns as much,
x < 1 < y when it turns less), keyframes and the median ms per frame (one thread), appends the
table to <out>/registration_sweep.md.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402
from rich.console import Console  # noqa: E402
from rich.table import Table  # noqa: E402

REPO_ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO_ROOT))

from benchmarks.provenance import run_heading, utc_stamp  # noqa: E402
from benchmarks.registration import parse_overrides  # noqa: E402
from server.datasets import open_dataset  # noqa: E402
from server.evaluation.metrics import associate_trajectories, evaluate, rotation_gain  # noqa: E402
from server.evaluation.trajectory import Trajectory  # noqa: E402
from server.pipeline import ground_truth_pose_at  # noqa: E402
from server.registration import Tracker  # noqa: E402
from server.registration.calibration import ColourToDepth  # noqa: E402
from server.registration.config import RegistrationConfig  # noqa: E402

cv2.setNumThreads(1)
console = Console()


def track_all(ds, frames, cfg: RegistrationConfig, true_keyframes: bool = False) -> dict:
    """ATE and RPE (metres, degrees), keyframes, per-frame times and the poses (N, 4, 4) of one
    run. ``true_keyframes``: every new keyframe is moved to its ground-truth pose as it is made
    (the tracker goes on from there), so that only the error of frames against their keyframe
    is left: what the keyframe chain costs is the difference to a normal run."""
    T0 = ground_truth_pose_at(ds, frames[0].timestamp)
    tracker = Tracker(ds.intrinsics, cfg, T0)
    to_depth = ColourToDepth(ds.intrinsics, cfg.depth, not ds.depth_registered)
    poses, ms = [], []
    for frame in frames:
        t0 = time.perf_counter()
        result = tracker.track(to_depth(frame.colour, frame.depth), frame.depth)
        made = tracker.update_keyframe()
        ms.append((time.perf_counter() - t0) * 1e3)
        poses.append(result.T_world_camera)
        T_true = ground_truth_pose_at(ds, frame.timestamp) if true_keyframes and made else None
        if T_true is not None and tracker.keyframe is not None:
            tracker.keyframe.T_world_keyframe = T_true.copy()
            tracker.T_world_last = T_true.copy()  # this frame is the keyframe
    stamps = np.array([f.timestamp for f in frames])
    est = Trajectory(stamps, np.array(poses))
    metrics = evaluate(ds.ground_truth, est)
    gain = rotation_gain(*associate_trajectories(ds.ground_truth, est))
    return {
        **metrics,
        "rotation_gain": (gain["est_on_gt"], gain["gt_on_est"]),
        "keyframes": tracker.keyframe_count,
        "median_ms": float(np.median(ms[1:])),
        "colour_registration": to_depth.mapping,
        "poses": est.poses,
    }


def load_frames(sequence: Path, frames: int | None) -> tuple:
    """The dataset and its first ``frames`` frames (all when None) in memory; exits when it
    has no ground truth to score against."""
    ds = open_dataset(sequence)
    if ds.ground_truth is None:
        raise SystemExit(f"{sequence} has no ground truth")
    n = len(ds) if frames is None else min(frames, len(ds))
    return ds, [ds[i] for i in range(n)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("sequence", type=Path)
    parser.add_argument("--frames", type=int, help="only the first N frames")
    parser.add_argument("--set", action="append", default=[], help="one run's changes")
    parser.add_argument("--out", type=Path, default=REPO_ROOT / "benchmarks" / "results")
    args = parser.parse_args()
    ds, frames = load_frames(args.sequence, args.frames)
    n = len(frames)
    runs = [("defaults", RegistrationConfig())]
    for change in args.set:
        overrides = parse_overrides(change.split())
        runs.append((change, RegistrationConfig().with_overrides(**overrides)))
    table = Table(title=f"{ds.name}, {n} frames, sparse + dense")
    columns = ("run", "ATE cm", "RPE/s cm", "RPE/s deg", "rotation gain", "keyframes", "median ms")
    for col in columns:
        table.add_column(col, justify="right")
    rows = []
    for name, cfg in runs:
        m = track_all(ds, frames, cfg)
        row = (
            name,
            f"{100 * m['ate_rmse_m']:.2f}",
            f"{100 * m['rpe_trans_per_second_m']:.2f}",
            f"{m['rpe_rot_per_second_deg']:.2f}",
            "{:.3f} / {:.3f}".format(*m["rotation_gain"]),
            str(m["keyframes"]),
            f"{m['median_ms']:.1f}",
        )
        rows.append(row)
        table.add_row(*row)
        console.print(f"{name}: ATE {row[1]} cm (colour registration {m['colour_registration']})")
    console.print(table)
    args.out.mkdir(parents=True, exist_ok=True)
    stamp = utc_stamp()
    lines = [
        *run_heading(stamp, ", one thread"),
        "| run | ATE cm | RPE/s cm | RPE/s deg | rotation gain | keyframes | median ms |",
        "|---|---:|---:|---:|---:|---:|---:|",
        *(f"| {' | '.join(r)} |" for r in rows),
    ]
    with open(args.out / "registration_sweep.md", "a") as f:
        f.write("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
