"""Registration benchmark: our tracker (sparse, sparse + dense) against Open3D's RGB-D odometry.

Every method runs in this one process, on the same frames, frame-to-frame (Open3D) or
frame-to-keyframe (ours), without loop closure, starting from the ground-truth pose of the first
frame, on one CPU thread. Only the per-frame registration call is timed: frames are loaded (and
converted to Open3D images) in an untimed pre-pass.

    python benchmarks/registration.py                        # every ../shared/data/* + demo
    python benchmarks/registration.py ../shared/data/synthetic_room0 --frames 30
    python benchmarks/registration.py ../shared/data/7scenes_a --stride 2 --methods ours_sparse

Prints one table per sequence, appends it to <out>/registration.md, updates <out>/registration.json
and writes <out>/trajectories/<run>/<method>.tum and <out>/<run>_trajectories.png, where <run> is
the sequence name with ``_nN`` / ``_sS`` added for --frames / --stride.

With --drop or --prior it measures instead our tracker on frames dropped as a busy server drops
them, with and without the device's own pose as a prior (exact, or drifting like a phone's VIO):

    python benchmarks/registration.py ../shared/data/synthetic_room0 \
        --drop none every2 every3 burst10 --prior none gt drifting

and writes <out>/registration_prior.md and <out>/registration_prior.json.
"""

from __future__ import annotations

import os

# One thread everywhere, set before numpy, OpenCV and Open3D start their thread pools.
THREAD_VARS = (
    "OMP_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "MKL_NUM_THREADS",
    "NUMEXPR_NUM_THREADS",
    "VECLIB_MAXIMUM_THREADS",
    "BLIS_NUM_THREADS",
)
for _var in THREAD_VARS:
    os.environ[_var] = "1"

import argparse  # noqa: E402
import datetime  # noqa: E402
import json  # noqa: E402
import logging  # noqa: E402
import platform  # noqa: E402
import shlex  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from dataclasses import dataclass, field  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import matplotlib  # noqa: E402
import numpy as np  # noqa: E402
import open3d as o3d  # noqa: E402
from rich.console import Console  # noqa: E402
from rich.markup import escape  # noqa: E402
from rich.table import Table  # noqa: E402
from tqdm import tqdm  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

REPO_ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO_ROOT))

from benchmarks.provenance import git_commit  # noqa: E402
from benchmarks.published import PAPERS, published  # noqa: E402
from server.datasets import RGBDFrame, open_dataset  # noqa: E402
from server.errors import DroneSimError  # noqa: E402
from server.evaluation.device_poses import (  # noqa: E402
    DeviceDrift,
    drifting_device_poses,
    exact_device_poses,
)
from server.evaluation.metrics import evaluate  # noqa: E402
from server.evaluation.trajectory import (  # noqa: E402
    Trajectory,
    associate,
    write_tum,  # noqa: E402
)
from server.geometry import Intrinsics, invert, rotation_angle_deg  # noqa: E402
from server.pipeline import ground_truth_pose_at, run_odometry  # noqa: E402
from server.registration import Tracker, TrackingState  # noqa: E402
from server.registration.calibration import ColourToDepth  # noqa: E402
from server.registration.config import RegistrationConfig  # noqa: E402

cv2.setNumThreads(1)
o3d.utility.set_max_threads(1)  # Open3D 0.20 runs on TBB, which ignores OMP_NUM_THREADS
o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)

logger = logging.getLogger("benchmarks.registration")
console = Console(width=max(Console().width, 180))  # wide table, also when piped

# Targets for our rows: (key, label, test).
TARGETS: tuple[tuple[str, str, Callable[[float], bool]], ...] = (
    ("ate_vs_legacy", "ATE <= 0.5x legacy", lambda v: v <= 0.5),
    ("lost", "0 lost", lambda v: v == 0),
    ("median_ms", "median <= 33 ms", lambda v: v <= 33.0),
    ("speedup_legacy", ">= 15x faster than legacy", lambda v: v >= 15.0),
    ("speedup_tensor", ">= 1.5x faster than tensor", lambda v: v >= 1.5),
)


@dataclass
class MethodRun:
    """One method's output on one sequence. Timings cover frames 1..N-1 (frame 0 has no call)."""

    poses: np.ndarray  # (N, 4, 4) T_world_camera, metres
    times_ms: list[float] = field(default_factory=list)
    cpu_s: float = 0.0  # process CPU time over the timed calls, to check the one-thread limit
    lost: int = 0
    weak: int | None = None  # ours only
    stage_ms: dict[str, float] = field(default_factory=dict)  # mean per stage (ours only)


class Clock:
    """Wall and CPU time of the calls made inside ``with clock:``."""

    def __init__(self, run: MethodRun) -> None:
        self.run = run

    def __enter__(self) -> None:
        self.wall, self.cpu = time.perf_counter(), time.process_time()

    def __exit__(self, *exc) -> None:
        self.run.times_ms.append((time.perf_counter() - self.wall) * 1e3)
        self.run.cpu_s += time.process_time() - self.cpu


# ---------------------------------------------------------------------------------- methods
# Our tracker's configuration: the defaults, with --set's changes (e.g. the photometric term).
BASE_CONFIG = RegistrationConfig()


def parse_overrides(items: list[str]) -> dict[str, dict]:
    """--set section.field=value ... -> {section: {field: value}} (values as YAML: numbers,
    booleans, strings)."""
    import yaml

    out: dict[str, dict] = {}
    for item in items:
        key, sep, value = item.partition("=")
        section, dot, name = key.partition(".")
        if not (sep and dot and section and name):
            raise argparse.ArgumentTypeError(f"--set wants section.field=value, got {item!r}")
        out.setdefault(section, {})[name] = yaml.safe_load(value)
    return out


def run_ours(
    frames: list[RGBDFrame],
    K: Intrinsics,
    T0: np.ndarray,
    bar,
    dense: bool,
    priors: np.ndarray | None = None,
) -> MethodRun:
    """Our frame-to-keyframe tracker; sparse only or sparse + dense refinement; ``priors``
    (N, 4, 4): the device's own T_device_camera per frame, given to the tracker as its prior."""
    config = BASE_CONFIG.with_overrides(solver={"dense": dense})
    tracker = Tracker(K, config, T_world_first=T0)
    to_depth = ColourToDepth(K, config.depth)  # where frames come in, as track and the server
    run = MethodRun(poses=np.empty((len(frames), 4, 4)), weak=0)
    stages: dict[str, list[float]] = {}
    for i, frame in enumerate(frames):
        prior = None if priors is None else priors[i]
        if i == 0:  # starts the first keyframe (and estimates the colour's registration)
            result = tracker.track(to_depth(frame.colour, frame.depth), frame.depth, prior)
        else:
            with Clock(run):  # the pose, then the keyframe work the server does after sending it
                colour = to_depth(frame.colour, frame.depth)
                result = tracker.track(colour, frame.depth, prior)
                tracker.update_keyframe()
            run.lost += result.state is TrackingState.LOST
            run.weak += result.state is TrackingState.WEAK
            for name, ms in result.timings_ms.items():
                stages.setdefault(name, []).append(ms)
        run.poses[i] = result.T_world_camera
        bar.update()
    run.stage_ms = {name: float(np.mean(v)) for name, v in stages.items()}
    return run


def run_o3d_legacy(frames: list[RGBDFrame], K: Intrinsics, T0: np.ndarray, bar) -> MethodRun:
    """Open3D ``compute_rgbd_odometry``, hybrid term, default OdometryOption, frame-to-frame.

    It returns T_target_source (source points -> target camera); with source = previous frame
    and target = current frame that is T_cur_prev, so T_world_cur = T_world_prev @ inv(T).
    """
    pinhole = o3d.camera.PinholeCameraIntrinsic(K.width, K.height, K.fx, K.fy, K.cx, K.cy)
    trunc = RegistrationConfig().depth.max_depth_m
    images = [
        o3d.geometry.RGBDImage.create_from_color_and_depth(
            o3d.geometry.Image(np.ascontiguousarray(f.colour)),
            o3d.geometry.Image(np.ascontiguousarray(f.depth, dtype=np.float32)),
            depth_scale=1.0,
            depth_trunc=trunc,
            convert_rgb_to_intensity=True,
        )
        for f in frames
    ]
    jacobian = o3d.pipelines.odometry.RGBDOdometryJacobianFromHybridTerm()
    option = o3d.pipelines.odometry.OdometryOption()
    run = MethodRun(poses=np.empty((len(frames), 4, 4)))
    run.poses[0] = T0
    bar.update()
    for i in range(1, len(frames)):
        with Clock(run):
            ok, T_cur_prev, _ = o3d.pipelines.odometry.compute_rgbd_odometry(
                images[i - 1], images[i], pinhole, np.eye(4), jacobian, option
            )
        if ok and np.all(np.isfinite(T_cur_prev)):
            run.poses[i] = run.poses[i - 1] @ np.linalg.inv(T_cur_prev)
        else:
            run.poses[i] = run.poses[i - 1]  # hold the last pose
            run.lost += 1
        bar.update()
    return run


def run_o3d_tensor(frames: list[RGBDFrame], K: Intrinsics, T0: np.ndarray, bar) -> MethodRun:
    """Open3D tensor ``rgbd_odometry_multi_scale``, Method.Hybrid on CPU, default criteria and
    depth_max, identity initialisation, frame-to-frame. Its ``transformation`` is T_target_source
    as for the legacy call; a singular system raises RuntimeError, counted as a lost frame."""
    odometry = o3d.t.pipelines.odometry
    intrinsics = o3d.core.Tensor(K.matrix, o3d.core.float64)
    identity = o3d.core.Tensor(np.eye(4), o3d.core.float64)
    images = [
        o3d.t.geometry.RGBDImage(
            o3d.t.geometry.Image(np.ascontiguousarray(f.colour)),
            o3d.t.geometry.Image(np.ascontiguousarray(f.depth, dtype=np.float32)),
        )
        for f in frames
    ]
    run = MethodRun(poses=np.empty((len(frames), 4, 4)))
    run.poses[0] = T0
    bar.update()
    for i in range(1, len(frames)):
        T_cur_prev = None
        with Clock(run):
            try:
                result = odometry.rgbd_odometry_multi_scale(
                    images[i - 1],
                    images[i],
                    intrinsics,
                    identity,
                    1.0,
                    method=odometry.Method.Hybrid,
                )
                if result.fitness > 0:
                    T_cur_prev = result.transformation.numpy()
            except RuntimeError:
                pass
        if T_cur_prev is not None and np.all(np.isfinite(T_cur_prev)):
            run.poses[i] = run.poses[i - 1] @ np.linalg.inv(T_cur_prev)
        else:
            run.poses[i] = run.poses[i - 1]
            run.lost += 1
        bar.update()
    return run


def run_ours_track(ds, first: int, n: int, bar) -> MethodRun:
    """``python -m server track`` on frames first..first+n-1: the tracker, then loop closure
    over its keyframes (registration.loops, on by default offline), every frame moved with its
    keyframe; no map. Times: the whole run per frame (loop closure included), one value per
    frame, as wall time over the frames."""
    run_started = time.perf_counter()
    cpu0 = time.process_time()
    odometry = run_odometry(
        ds, BASE_CONFIG, max_frames=n, progress=False, start=first, keep_room=False
    )
    bar.update(n)
    wall_ms = (time.perf_counter() - run_started) * 1e3
    states = [r.state for r in odometry.results]
    return MethodRun(
        poses=odometry.trajectory.poses,
        times_ms=[wall_ms / n] * n,
        cpu_s=time.process_time() - cpu0,
        lost=sum(s is TrackingState.LOST for s in states[1:]),
        weak=sum(s is TrackingState.WEAK for s in states[1:]),
    )


# key -> (label, runner)
METHODS: dict[str, tuple[str, Callable[..., MethodRun]]] = {
    "ours_sparse": ("ours sparse", lambda *a: run_ours(*a, dense=False)),
    "ours_dense": ("ours sparse+dense", lambda *a: run_ours(*a, dense=True)),
    # Needs the dataset, not frames in memory: run by benchmark_sequence itself.
    "ours_track": ("ours track (+loops)", lambda *a: None),
    "o3d_legacy": ("Open3D legacy", run_o3d_legacy),
    "o3d_tensor": ("Open3D tensor", run_o3d_tensor),
}


# ---------------------------------------------------------------------------------- one sequence
def load_frames(path: Path, frames: int | None, stride: int):
    """The dataset, its selected frames (in memory), their GT poses and the nominal frame rate."""
    ds = open_dataset(path)
    if ds.ground_truth is None:
        raise DroneSimError(f"{path}: no ground truth, cannot benchmark")
    stamps = np.asarray(ds.timestamps)
    indices = np.arange(len(ds) if frames is None else min(frames, len(ds)))[::stride]
    idx_frame, idx_gt = associate(stamps[indices], ds.ground_truth.timestamps, 0.02)
    if len(idx_frame) < 2:
        raise DroneSimError(f"{path}: fewer than 2 selected frames have ground truth")
    indices = indices[idx_frame[0] :]  # start at the first frame with a ground-truth pose
    gt_poses = ds.ground_truth.poses[idx_gt]
    loaded = [ds[int(i)] for i in tqdm(indices, desc=f"{path.name} load", unit="frame")]
    fps = 1.0 / float(np.median(np.diff(stamps))) if len(stamps) > 1 else float("nan")
    return ds, loaded, gt_poses, fps


def motion_stats(gt_poses: np.ndarray, fps: float, stride: int) -> dict[str, float]:
    """Camera speed the selected frames show when played at the nominal frame rate."""
    rel = np.linalg.inv(gt_poses[:-1]) @ gt_poses[1:]
    dist = np.linalg.norm(rel[:, :3, 3], axis=1)
    angle = np.array([rotation_angle_deg(T) for T in rel])
    return {
        "stride": stride,
        "fps": fps,
        "mean_speed_m_s": float(dist.mean() * fps),
        "max_speed_m_s": float(dist.max() * fps),
        "mean_rot_deg_s": float(angle.mean() * fps),
        "max_rot_deg_s": float(angle.max() * fps),
    }


def summarise(run: MethodRun, metrics: dict, n_frames: int) -> dict:
    t = np.asarray(run.times_ms)
    wall_s = t.sum() / 1e3
    return {
        **metrics,
        "frames": n_frames,
        "lost": run.lost,
        "weak": run.weak,
        "median_ms": float(np.median(t)),
        "p90_ms": float(np.percentile(t, 90)),
        "mean_ms": float(t.mean()),
        "cpu_per_wall": float(run.cpu_s / wall_s) if wall_s else None,
        "stage_mean_ms": run.stage_ms,
    }


def add_ratios(results: dict[str, dict]) -> None:
    """ATE and speed ratios against the Open3D baselines, and the targets for our rows."""
    legacy, tensor = results.get("o3d_legacy"), results.get("o3d_tensor")
    for key, r in results.items():
        r["ate_vs_legacy"] = r["ate_rmse_m"] / legacy["ate_rmse_m"] if legacy else None
        r["speedup_legacy"] = legacy["median_ms"] / r["median_ms"] if legacy else None
        r["speedup_tensor"] = tensor["median_ms"] / r["median_ms"] if tensor else None
        if key.startswith("ours"):
            r["targets"] = {
                label: (None if r[k] is None else bool(ok(r[k]))) for k, label, ok in TARGETS
            }


COLUMNS = (  # (key, header, format); a target mark follows the figure where one applies
    ("ate_rmse_m", "ATE [cm]", lambda v: f"{v * 100:.2f}"),
    ("rpe_trans_per_frame_m", "RPE/fr [mm]", lambda v: f"{v * 1000:.2f}"),
    ("rpe_rot_per_frame_deg", "RPE/fr [deg]", lambda v: f"{v:.3f}"),
    ("rpe_trans_per_second_m", "RPE/s [cm]", lambda v: f"{v * 100:.2f}"),
    ("rpe_rot_per_second_deg", "RPE/s [deg]", lambda v: f"{v:.2f}"),
    ("lost", "lost (0)", str),
    ("weak", "weak", str),
    ("median_ms", "median ms (<=33)", lambda v: f"{v:.1f}"),
    ("p90_ms", "p90 ms", lambda v: f"{v:.1f}"),
    ("ate_vs_legacy", "ATE/legacy (<=0.5)", lambda v: f"{v:.2f}x"),
    ("speedup_legacy", "x legacy (>=15)", lambda v: f"{v:.1f}x"),
    ("speedup_tensor", "x tensor (>=1.5)", lambda v: f"{v:.2f}x"),
)
TARGET_OF = {key: label for key, label, _ in TARGETS}


def table_rows(results: dict[str, dict]) -> list[list[tuple[str, bool | None]]]:
    """Per method: (cell text, target met?) for each column; None where no target applies."""
    rows = []
    for key, r in results.items():
        cells = [(METHODS[key][0], None)]
        for col, _, fmt in COLUMNS:
            value = r.get(col)
            if value is None or (isinstance(value, float) and not np.isfinite(value)):
                cells.append(("-", None))
                continue
            cells.append((fmt(value), r.get("targets", {}).get(TARGET_OF.get(col))))
        rows.append(cells)
    return rows


def rich_table(title: str, rows) -> Table:
    table = Table(title=title)
    table.add_column("method", style="bold")
    for _, header, _ in COLUMNS:
        table.add_column(escape(header), justify="right")
    for cells in rows:
        table.add_row(
            *(
                text if ok is None else f"{text} [{'green]✓' if ok else 'red]✗'}[/]"
                for text, ok in cells
            )
        )
    return table


def markdown_table(rows) -> str:
    lines = [
        "| method | " + " | ".join(h for _, h, _ in COLUMNS) + " |",
        "|---" + "|---:" * len(COLUMNS) + "|",
    ]
    for cells in rows:
        lines.append(
            "| "
            + " | ".join(
                text if ok is None else f"{text} {'✓' if ok else '✗'}" for text, ok in cells
            )
            + " |"
        )
    return "\n".join(lines)


def plot_topview(
    path: Path,
    title: str,
    gt: np.ndarray,
    estimates: dict[str, np.ndarray],
    labels: dict[str, str] | None = None,
) -> None:
    """GT and estimated camera positions (poses (N, 4, 4)) on the two axes along which GT
    extends most; ``labels`` name the estimates (default: the methods' names)."""
    extent = np.ptp(gt[:, :3, 3], axis=0)
    a, b = sorted(np.argsort(extent)[-2:])
    fig, ax = plt.subplots(figsize=(7, 6))
    ax.plot(gt[:, a, 3], gt[:, b, 3], "k-", lw=2.5, label="ground truth")
    for name, poses in estimates.items():
        label = labels[name] if labels is not None else METHODS[name][0]
        ax.plot(poses[:, a, 3], poses[:, b, 3], lw=1.2, label=label)
    ax.plot(gt[0, a, 3], gt[0, b, 3], "ko", ms=6)
    ax.set_xlabel(f"{'xyz'[a]} [m]")
    ax.set_ylabel(f"{'xyz'[b]} [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(f"{title}: top view, unaligned, from the GT first pose", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def run_name_of(name: str, args) -> str:
    """The sequence name, with _nN / _sS for --frames / --stride, naming its output files."""
    frames = f"_n{args.frames}" if args.frames else ""
    changed = "".join(f"_{k}={v}" for k, v in args.set)
    return name + frames + (f"_s{args.stride}" if args.stride > 1 else "") + changed


def benchmark_sequence(name: str, path: Path, args, header: dict) -> dict:
    run_name = run_name_of(name, args)
    ds, frames, gt_poses, fps = load_frames(path, args.frames, args.stride)
    stamps = np.array([f.timestamp for f in frames])
    motion = motion_stats(gt_poses, fps, args.stride)
    results, estimates = {}, {}
    for key in args.methods:
        label, runner = METHODS[key]
        if key == "ours_track" and args.stride != 1:
            console.print(f"{run_name}: ours_track skipped (it reads every frame; --stride 1)")
            continue
        with tqdm(total=len(frames), desc=f"{run_name} {label}", unit="frame") as bar:
            if key == "ours_track":
                run = run_ours_track(ds, frames[0].index, len(frames), bar)
            else:
                run = runner(frames, ds.intrinsics, gt_poses[0], bar)
        est = Trajectory(stamps, run.poses)
        write_tum(args.out / "trajectories" / run_name / f"{key}.tum", est)
        metrics = evaluate(ds.ground_truth, est)
        results[key] = summarise(run, metrics, len(frames))
        estimates[key] = run.poses
    add_ratios(results)

    speed = (
        f"{len(frames)} frames, stride {args.stride} at {fps:.0f} Hz: camera "
        f"{motion['mean_speed_m_s']:.2f} m/s (max {motion['max_speed_m_s']:.2f}), "
        f"{motion['mean_rot_deg_s']:.0f} deg/s (max {motion['max_rot_deg_s']:.0f})"
    )
    rows = table_rows(results)
    console.print(rich_table(f"{run_name} — {speed}", rows))
    targets = "; ".join(label for _, label, _ in TARGETS)
    console.print(f"targets for our rows: {targets}")
    others = published(name)
    cited = ""
    if others:
        papers = ", ".join(f"{p} {ate * 100:.1f} cm ({PAPERS[p]})" for p, ate in others.items())
        cited = (
            "Published ATE RMSE on this sequence (the papers' own figures, whole sequence, not "
            f"measured here): {papers}.\n\n"
        )
        console.print(cited.strip())

    png = args.out / f"{run_name}_trajectories.png"
    plot_topview(png, run_name, gt_poses, estimates)
    with open(args.out / "registration.md", "a") as md:
        md.write(
            f"\n### {run_name}\n\n{speed}. Targets for our rows: {targets}.\n\n"
            f"{markdown_table(rows)}\n\n{cited}"
            f"Trajectories: `trajectories/{run_name}/`, plot: `{png.name}`.\n"
        )
    return {
        "header": header,
        "sequence": str(path),
        "motion": motion,
        "methods": results,
        "published_ate_m": others,
    }


# ---------------------------------------------------------------------------------- device prior
PRIORS = ("none", "gt", "drifting")
DROPS = ("none", "every2", "every3", "burst10")
PRIOR_TARGETS = "with a prior: 0 lost, and ATE <= the same case without a prior"


def kept_frames(n: int, drop: str) -> np.ndarray:
    """Indices of the frames that reach the tracker, of n: ``none`` all of them; ``everyN`` only
    every N-th (a server N times too slow); ``burstN`` N in a row lost after every 3N received."""
    i = np.arange(n)
    if drop == "none":
        return i
    if drop.startswith("every"):
        return i[:: int(drop[5:])]
    if drop.startswith("burst"):
        m = int(drop[5:])
        return i[i % (4 * m) < 3 * m]
    raise ValueError(f"unknown drop pattern {drop!r}")


def drop_pattern(text: str) -> str:
    """argparse type: none, everyN (N >= 2) or burstN (N >= 1)."""
    ok = text == "none" or (
        text[:5] in ("every", "burst")
        and text[5:].isdigit()
        and int(text[5:]) >= (2 if text.startswith("every") else 1)
    )
    if not ok:
        raise argparse.ArgumentTypeError(f"{text!r}: use none, everyN (N >= 2) or burstN")
    return text


def prior_drift(gt: np.ndarray, prior: np.ndarray) -> dict[str, float]:
    """How far a device pose drifted from the truth over the sequence: the prior's last pose,
    aligned at the first, against the truth; and the path length it drifted over."""
    T_world_device = gt[0] @ invert(prior[0])
    E = invert(gt[-1]) @ T_world_device @ prior[-1]
    path = float(np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1).sum())
    return {
        "path_m": path,
        "end_drift_m": float(np.linalg.norm(E[:3, 3])),
        "end_drift_deg": rotation_angle_deg(E),
    }


PRIOR_COLUMNS = (  # (key, header, format)
    ("frames", "frames", str),
    ("ate_rmse_m", "ATE [cm]", lambda v: f"{v * 100:.2f}"),
    ("ate_vs_none_m", "ATE - no prior [mm]", lambda v: f"{v * 1000:+.3f}"),
    ("rpe_trans_per_frame_m", "RPE/fr [mm]", lambda v: f"{v * 1000:.2f}"),
    ("rpe_rot_per_frame_deg", "RPE/fr [deg]", lambda v: f"{v:.3f}"),
    ("rpe_trans_per_second_m", "RPE/s [cm]", lambda v: f"{v * 100:.2f}"),
    ("rpe_rot_per_second_deg", "RPE/s [deg]", lambda v: f"{v:.2f}"),
    ("lost", "lost", str),
    ("weak", "weak", str),
    ("median_ms", "median ms", lambda v: f"{v:.1f}"),
    ("p90_ms", "p90 ms", lambda v: f"{v:.1f}"),
)


def prior_rows(results: dict[str, dict]) -> list[list[str]]:
    """One row per case: drop, prior, method, the columns; ✓/✗ after lost and ATE of prior rows
    (0 lost; ATE not above the same drop and method without a prior)."""
    rows = []
    for r in results.values():
        cells = [r["drop"], r["prior"], METHODS[r["method"]][0]]
        for col, _, fmt in PRIOR_COLUMNS:
            value = r.get(col)
            text = "-" if value is None or not np.isfinite(value) else fmt(value)
            target = r.get("targets", {}).get(col)
            cells.append(text if target is None else f"{text} {'✓' if target else '✗'}")
        rows.append(cells)
    return rows


def benchmark_prior(name: str, path: Path, args, header: dict) -> dict:
    """Our tracker on the sequence with frames dropped, without and with a device prior."""
    run_name = run_name_of(name, args)
    ds, frames, _, fps = load_frames(path, args.frames, args.stride)
    stamps = np.array([f.timestamp for f in frames])
    gt_list = [ground_truth_pose_at(ds, t) for t in stamps]
    if any(T is None for T in gt_list):
        raise DroneSimError(f"{path}: a selected frame has no ground-truth pose")
    gt = np.array(gt_list)
    drift = DeviceDrift(seed=args.seed)
    priors = {
        "none": None,
        "gt": exact_device_poses(gt, args.seed),
        "drifting": drifting_device_poses(gt, stamps, drift),
    }
    drifted = prior_drift(gt, priors["drifting"])
    methods = [m for m in args.methods if m in ("ours_sparse", "ours_dense")] or ["ours_dense"]
    results: dict[str, dict] = {}
    for drop in args.drop:
        keep = kept_frames(len(frames), drop)
        kept = [frames[i] for i in keep]
        for prior in args.prior:
            poses = priors[prior]
            for key in methods:
                label = f"{run_name} {drop} prior={prior} {METHODS[key][0]}"
                with tqdm(total=len(kept), desc=label, unit="frame") as bar:
                    run = run_ours(
                        kept,
                        ds.intrinsics,
                        gt[keep[0]],
                        bar,
                        dense=key == "ours_dense",
                        priors=None if poses is None else poses[keep],
                    )
                metrics = evaluate(ds.ground_truth, Trajectory(stamps[keep], run.poses))
                r = summarise(run, metrics, len(kept))
                r.update(drop=drop, prior=prior, method=key)
                base = results.get(f"{drop}/none/{key}")
                if prior != "none" and base is not None:
                    r["ate_vs_none_m"] = r["ate_rmse_m"] - base["ate_rmse_m"]
                if prior != "none":
                    r["targets"] = {
                        "lost": r["lost"] == 0,
                        "ate_rmse_m": None
                        if base is None
                        else bool(r["ate_rmse_m"] <= base["ate_rmse_m"]),
                    }
                results[f"{drop}/{prior}/{key}"] = r

    title = (
        f"{run_name}: {len(frames)} frames at {fps:.0f} Hz; drifting prior (seed {args.seed}): "
        f"{drift.translation_fraction * 100:.0f} % of path, {drift.yaw_deg_per_s} deg/s yaw, "
        f"noise {drift.noise_m * 1000:.0f} mm / {drift.noise_deg} deg; over the "
        f"{drifted['path_m']:.2f} m path it ends {drifted['end_drift_m'] * 100:.1f} cm and "
        f"{drifted['end_drift_deg']:.2f} deg off"
    )
    headers = ["drop", "prior", "method", *(h for _, h, _ in PRIOR_COLUMNS)]
    rows = prior_rows(results)
    table = Table(title=title)
    for h in headers:
        table.add_column(escape(h), justify="left" if h in headers[:3] else "right")
    for cells in rows:
        table.add_row(*(escape(c) for c in cells))
    console.print(table)
    console.print(f"targets: {PRIOR_TARGETS}")
    with open(args.out / "registration_prior.md", "a") as md:
        md.write(
            f"\n### {run_name}\n\n{title}. Targets: {PRIOR_TARGETS}.\n\n"
            "| " + " | ".join(headers) + " |\n"
            "|---|---|---"
            + "|---:" * len(PRIOR_COLUMNS)
            + "|\n"
            + "".join("| " + " | ".join(c) + " |\n" for c in rows)
        )
    return {"header": header, "sequence": str(path), "prior_drift": drifted, "cases": results}


# ---------------------------------------------------------------------------------- CLI
def default_sequences() -> list[tuple[str, Path]]:
    data = REPO_ROOT.parent / "shared" / "data"
    found = [(p.name, p) for p in sorted(data.iterdir()) if p.is_dir()] if data.is_dir() else []
    try:
        from server.datasets.demo import demo_sequence_path
    except ImportError as exc:
        console.print(f"[yellow]note: demo sequence skipped ({exc})[/]")
        return found
    try:
        found.append(("demo", Path(demo_sequence_path())))
    except DroneSimError as exc:
        console.print(f"[yellow]note: demo sequence skipped: {exc}[/]")
    return found


def run_header(argv: list[str]) -> dict:
    return {
        "date": datetime.datetime.now().isoformat(timespec="seconds"),
        "machine": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "opencv": cv2.__version__,
        "open3d": o3d.__version__,
        "threads": {
            "env": {v: os.environ[v] for v in THREAD_VARS},
            "cv2": cv2.getNumThreads(),
            "open3d_max": o3d.utility.get_max_threads(),
        },
        "command": shlex.join(["python", *argv]),
    }


def parse_args(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "sequences",
        nargs="*",
        type=Path,
        help="TUM-layout folders (default: every ../shared/data/* and the demo)",
    )
    parser.add_argument(
        "--demo-seeds",
        nargs="+",
        type=int,
        default=[],
        metavar="SEED",
        help="also synthetic rooms generated as the demo is, with these seeds (another room, "
        "path and noise each; cached like the demo): sequences no setting was chosen on",
    )
    parser.add_argument("--frames", type=int, help="use only the first N frames of each sequence")
    parser.add_argument(
        "--stride",
        type=int,
        default=1,
        help="use every S-th frame, to emulate S times faster motion",
    )
    parser.add_argument("--methods", nargs="+", choices=list(METHODS), default=list(METHODS))
    parser.add_argument("--out", type=Path, default=REPO_ROOT / "benchmarks" / "results")
    parser.add_argument(
        "--drop",
        nargs="+",
        type=drop_pattern,
        help=f"frames dropped: none, everyN (only every N-th arrives), burstN (N lost after "
        f"every 3N); measures our tracker with and without a prior (default with --prior: "
        f"{' '.join(DROPS)})",
    )
    parser.add_argument(
        "--prior",
        nargs="+",
        choices=PRIORS,
        help="the device pose given to our tracker: none, gt (exact, in another world frame), "
        f"drifting (like a phone's VIO) (default with --drop: {' '.join(PRIORS)})",
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of the simulated device pose")
    parser.add_argument(
        "--set",
        nargs="+",
        default=[],
        metavar="SECTION.FIELD=VALUE",
        help="change our tracker's registration config, e.g. solver.photometric_weight=0.5 "
        "(the run's name says so)",
    )
    args = parser.parse_args(argv)
    global BASE_CONFIG
    try:
        BASE_CONFIG = RegistrationConfig().with_overrides(**parse_overrides(args.set))
    except (argparse.ArgumentTypeError, DroneSimError) as exc:
        parser.error(str(exc))
    args.set = [(k.split("=")[0].rsplit(".", 1)[-1], k.split("=", 1)[1]) for k in args.set]
    args.prior_mode = args.drop is not None or args.prior is not None
    if args.prior_mode:
        args.drop = args.drop or list(DROPS)
        args.prior = [p for p in PRIORS if p in (args.prior or PRIORS)]
    if args.stride < 1 or (args.frames is not None and args.frames < 2):
        parser.error("need --stride >= 1 and --frames >= 2")
    args.methods = [m for m in METHODS if m in args.methods]  # keep the canonical order
    return args


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    args = parse_args(argv)
    header = run_header([sys.argv[0], *argv])
    threads = header["threads"]
    console.print(
        f"[bold]Registration benchmark[/] {header['date']}  {header['machine']}, "
        f"{header['cpu_count']} CPUs; python {header['python']}, numpy {header['numpy']}, "
        f"opencv {header['opencv']}, open3d {header['open3d']}\n"
        f"threads: {', '.join(f'{k}=1' for k in THREAD_VARS)}, cv2.setNumThreads(1) -> "
        f"{threads['cv2']}, open3d.utility.set_max_threads(1) -> {threads['open3d_max']}\n"
        f"command: {header['command']}"
    )
    sequences = [(p.name, p) for p in args.sequences]
    if args.demo_seeds:
        from server.datasets.demo import DemoSpec, demo_sequence_path

        sequences += [
            (f"demo_seed{seed}", Path(demo_sequence_path(DemoSpec(seed=seed))))
            for seed in args.demo_seeds
        ]
    sequences = sequences or default_sequences()

    args.out.mkdir(parents=True, exist_ok=True)
    stem = "registration_prior" if args.prior_mode else "registration"
    md_path, json_path = args.out / f"{stem}.md", args.out / f"{stem}.json"
    header["commit"] = git_commit()
    with open(md_path, "a") as md:
        md.write(
            f"\n## Run {header['date']}\n\n"
            f"- commit: {header['commit']}\n"
            f"- machine: {header['machine']} ({header['processor']}), "
            f"{header['cpu_count']} CPUs, all methods on 1 thread\n"
            f"- python {header['python']}, numpy {header['numpy']}, "
            f"opencv {header['opencv']}, open3d {header['open3d']}\n"
            f"- command: `{header['command']}`\n"
        )
    stored = json.loads(json_path.read_text()) if json_path.is_file() else {}
    failed = 0
    for name, path in sequences:
        try:
            bench = benchmark_prior if args.prior_mode else benchmark_sequence
            result = bench(name, path, args, header)
        except DroneSimError as exc:
            console.print(f"[red]{name}: skipped: {exc}[/]")
            failed += 1
            continue
        stored[run_name_of(name, args)] = result
        tmp = json_path.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(stored, indent=1, sort_keys=False) + "\n")
        tmp.replace(json_path)
    console.print(f"results: {md_path}, {json_path}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
