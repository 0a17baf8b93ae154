"""Where a sequence's ATE comes from: the ground truth's own glitches, the keyframe chain, and
the frames against their keyframe (issue 15's 7scenes_a row).

1. Our tracker (defaults, as ``track``) over the sequence; its motion over every span of 1, 2,
   4 and 8 frames is compared with the ground truth's and with other methods' trajectories
   (``--against``, e.g. the Open3D rows of ``benchmarks/registration.py``). A stretch where the
   ground truth moves more than ``--threshold-mm`` differently from every method while two of
   them agree within ``--agree-mm`` is listed (server/evaluation/ground_truth.py): two
   independent methods see the same motion in the images, the ground truth another.
2. The floor those stretches set: the ground truth with just those stretches' motion replaced
   by ours, scored against the ground truth. A method that followed the images perfectly would
   score it. Our ATE against that corrected ground truth is printed beside.
3. The same tracker with every new keyframe moved to its true pose as it is made: the ATE left
   is the frames' error against their keyframe; the rest of the normal run's is the chain's.
4. With ``--there-and-back N``: the first N frames played forward then back
   (``server.datasets.there_and_back``) tracked as ``track`` does with loop closure off and on,
   each scored against the ground truth and against the ground truth cleared of the stretches
   of 2 (replayed the same way): does a loop correction that looks worse against the first only
   meet the ground truth's glitch twice, once each way?

    python benchmarks/ground_truth_check.py ../shared/data/7scenes_a \\
        --against benchmarks/results/trajectories/7scenes_a/o3d_legacy.tum \\
        --against benchmarks/results/trajectories/7scenes_a/o3d_tensor.tum

Appends a table to benchmarks/results/ground_truth_check.md and draws
``<out>/<sequence>_ground_truth_steps.png`` (step lengths per frame, the listed ones marked).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import copy  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

REPO_ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO_ROOT))

from benchmarks.provenance import run_heading, utc_stamp  # noqa: E402
from benchmarks.registration_sweep import load_frames, track_all  # noqa: E402
from server.datasets.there_and_back import ThereAndBack  # noqa: E402
from server.evaluation.ground_truth import disputed_stretches, with_stretches_replaced  # noqa: E402
from server.evaluation.metrics import associate_trajectories, evaluate  # noqa: E402
from server.evaluation.trajectory import Trajectory, associate, read_tum  # noqa: E402
from server.pipeline import run_odometry  # noqa: E402
from server.registration.config import RegistrationConfig  # noqa: E402


def _on_frames(traj: Trajectory, stamps: np.ndarray) -> np.ndarray:
    """The trajectory's poses at these timestamps (every frame must be there)."""
    idx_frame, idx_traj = associate(stamps, traj.timestamps, 0.02)
    if len(idx_frame) < len(stamps):
        raise SystemExit(f"a trajectory lacks {len(stamps) - len(idx_frame)} of the frames")
    return traj.poses[idx_traj]


def _step_mm(poses: np.ndarray) -> np.ndarray:
    """Each frame's translation to the next (N-1,), millimetres."""
    steps = np.einsum("nij,njk->nik", np.linalg.inv(poses[:-1]), poses[1:])
    return 1e3 * np.linalg.norm(steps[:, :3, 3], axis=1)


def _there_and_back_rows(ds, cleared: Trajectory, cases: list[int]) -> list[str]:
    """Loop closure off and on over each there-and-back case, scored against the ground truth
    and against ``cleared`` (the ground truth without its disputed stretches), as table rows."""
    ds_cleared = copy.copy(ds)
    ds_cleared.ground_truth = cleared
    rows = [
        "there and back: ATE cm against the ground truth / against it cleared of the stretches",
        "",
        "| case | loops | odometry | loop closure |",
        "|---|---:|---|---|",
    ]
    on = RegistrationConfig().with_overrides(loops={"enabled": True})
    for n in cases:
        played, played_cleared = ThereAndBack(ds, n), ThereAndBack(ds_cleared, n)
        print(f"there and back {n}: odometry, then with loop closure ...", flush=True)
        odometry = run_odometry(played, progress=False, keep_room=False).trajectory
        run = run_odometry(played, on, progress=False)
        found = (run.summary.get("loops") or {}).get("found", 0)

        def cm(truth: Trajectory, est: Trajectory) -> str:
            return f"{100 * evaluate(truth, est)['ate_rmse_m']:.2f}"

        rows.append(
            f"| {ds.name} {n} | {found} "
            f"| {cm(played.ground_truth, odometry)} / {cm(played_cleared.ground_truth, odometry)} "
            f"| {cm(played.ground_truth, run.trajectory)} / "
            f"{cm(played_cleared.ground_truth, run.trajectory)} |"
        )
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("sequence", type=Path)
    parser.add_argument("--frames", type=int, help="only the first N frames")
    parser.add_argument("--against", type=Path, action="append", default=[],
                        help="another method's TUM trajectory over the same frames")  # fmt: skip
    parser.add_argument("--threshold-mm", type=float, default=20.0)
    parser.add_argument("--agree-mm", type=float, default=10.0)
    parser.add_argument("--there-and-back", type=int, nargs="*", default=[], metavar="N")
    parser.add_argument("--out", type=Path, default=REPO_ROOT / "benchmarks" / "results")
    args = parser.parse_args()
    ds, frames = load_frames(args.sequence, args.frames)
    n = len(frames)
    cfg = RegistrationConfig()
    print(f"{ds.name}: tracking {n} frames (defaults) ...", flush=True)
    ours = track_all(ds, frames, cfg)
    print("tracking again, each new keyframe put at its true pose ...", flush=True)
    pinned = track_all(ds, frames, cfg, true_keyframes=True)

    est = Trajectory(np.array([f.timestamp for f in frames]), ours["poses"])
    gt, est = associate_trajectories(ds.ground_truth, est)
    stamps = est.timestamps
    others = [(p.stem, _on_frames(read_tum(p), stamps)) for p in args.against]
    estimates = [est.poses, *(poses for _, poses in others)]
    print("checking the ground truth against the methods ...", flush=True)
    stretches = disputed_stretches(
        gt.poses, estimates, args.threshold_mm / 1e3, args.agree_mm / 1e3
    )
    cleared = Trajectory(stamps, with_stretches_replaced(gt.poses, est.poses, stretches))
    floor = evaluate(gt, cleared)["ate_rmse_m"]
    ours_on_cleared = evaluate(cleared, est)["ate_rmse_m"]

    methods = ", ".join(["ours", *(name for name, _ in others)])
    lines = [
        *run_heading(utc_stamp(), ", one thread"),
        f"{ds.name}, {len(stamps)} frames; stretches where the ground truth differs from every "
        f"method ({methods}) by more than {args.threshold_mm:g} mm and two of them agree within "
        f"{args.agree_mm:g} mm:\n",
        "| frames | ground truth moves mm, deg | nearest method differs mm, deg "
        "| two methods differ mm |",
        "|---|---|---|---:|",
    ]
    for s in stretches:
        lines.append(
            f"| {s.first} -> {s.last} | {1e3 * s.truth_m:.1f}, {s.truth_deg:.2f} "
            f"| {1e3 * s.disagreement_m:.1f}, {s.disagreement_deg:.2f} "
            f"| {1e3 * s.agreement_m:.1f} |"
        )
    lines += [
        "",
        "| figure | ATE cm |",
        "|---|---:|",
        f"| ours against the ground truth | {100 * ours['ate_rmse_m']:.2f} |",
        f"| the floor: the ground truth without the stretches above, against the ground truth "
        f"| {100 * floor:.2f} |",
        f"| ours against the ground truth without those stretches | {100 * ours_on_cleared:.2f} |",
        f"| ours with every keyframe at its true pose (frames against keyframes only) "
        f"| {100 * pinned['ate_rmse_m']:.2f} |",
        f"| keyframes | {ours['keyframes']} |",
    ]
    if args.there_and_back:
        lines += ["", *_there_and_back_rows(ds, cleared, args.there_and_back)]
    print("\n".join(lines))
    args.out.mkdir(parents=True, exist_ok=True)
    with open(args.out / "ground_truth_check.md", "a") as f:
        f.write("\n".join(lines) + "\n")

    fig, ax = plt.subplots(figsize=(11, 4))
    idx = np.arange(len(stamps) - 1)
    ax.plot(idx, _step_mm(gt.poses), label="ground truth", color="black", lw=1.2)
    for name, P in [("ours", est.poses), *others]:
        ax.plot(idx, _step_mm(P), label=name, lw=0.8, alpha=0.8)
    for s in stretches:
        ax.axvspan(s.first, s.last, color="red", alpha=0.2, lw=0)
    ax.set_xlabel("frame")
    ax.set_ylabel("step to the next frame [mm]")
    ax.set_title(f"{ds.name}: frame steps (red: the ground truth moves as no method sees)")
    ax.legend(loc="upper right")
    picture = args.out / f"{ds.name}_ground_truth_steps.png"
    fig.tight_layout()
    fig.savefig(picture, dpi=110)
    print(f"picture: {picture}")


if __name__ == "__main__":
    main()
