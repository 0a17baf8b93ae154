"""Tracking latency alone, beside TSDF fusion in a thread, and beside fusion in another process.

Why each session's map lives in a process of its own (server/sessions/mapping.py): Open3D's
``VoxelBlockGrid.integrate`` holds the GIL for its whole call, so fusion in a thread of the
tracking process stalls tracking. Tracks the first frames of a sequence at 15 fps (sleeping out
each frame's period) while a fusion runs every 200 ms (Open3D on one thread, the fusing thread
niced +10, as in the server), and prints tracking's median and p95 per case, against the target
that fusion in another process costs tracking's p95 at most 20 % over alone.

    python benchmarks/fusion_beside_tracking.py [SEQUENCE] [--frames 150]
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import subprocess
import sys
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # run from anywhere, installed or not

import cv2  # noqa: E402
import numpy as np  # noqa: E402
import open3d as o3d  # noqa: E402

from server.datasets import open_dataset  # noqa: E402
from server.mapping.tsdf import TSDFMap  # noqa: E402
from server.registration import Tracker  # noqa: E402
from server.sessions.mapping import MAPPING_NICE, lower_this_threads_priority  # noqa: E402

FPS, FUSE_PERIOD_S, TARGET_P95_RATIO = 15.0, 0.2, 1.2


def fuse_until(stop, frames: list, K, poses: np.ndarray) -> None:
    """Fuse frames with their ground-truth poses, one every FUSE_PERIOD_S, until ``stop``."""
    lower_this_threads_priority(MAPPING_NICE)
    o3d.utility.set_max_threads(1)
    tsdf, i = TSDFMap(), 0
    while not stop.is_set():
        f = frames[i % len(frames)]
        tsdf.integrate(f.colour, f.depth, K, poses[i % len(frames)])
        i += 1
        time.sleep(FUSE_PERIOD_S)


def track_at_camera_rate(frames: list, K) -> np.ndarray:
    """Wall ms of each ``Tracker.track`` call (the pose), frames paced at FPS."""
    tracker, wall = Tracker(K), []
    for f in frames:
        t0 = time.perf_counter()
        result = tracker.track(f.colour, f.depth)
        wall.append((time.perf_counter() - t0) * 1e3)
        if result.keyframe_due:
            tracker.update_keyframe()
        time.sleep(max(0.0, 1 / FPS - (time.perf_counter() - t0)))
    return np.array(wall[1:])  # frame 0 makes the first keyframe


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "sequence", nargs="?", default=str(REPO.parent / "shared" / "data" / "7scenes_a")
    )
    parser.add_argument("--frames", type=int, default=150)
    args = parser.parse_args()
    dataset = open_dataset(args.sequence)
    # In memory first: loading from disk in the loops would change the pace being measured.
    frames = [dataset[i] for i in range(min(args.frames, len(dataset)))]
    K, poses = dataset.intrinsics, dataset.ground_truth.poses
    cv2.setNumThreads(2)
    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True
    ).stdout.strip()
    print(
        f"{dataset.name}, {len(frames)} frames at {FPS:g} fps, a fusion every "
        f"{FUSE_PERIOD_S * 1e3:.0f} ms; commit {commit}"
    )

    def beside(worker, stop) -> np.ndarray:
        """Tracking timed while ``worker`` (a Thread or Process class) fuses until ``stop``."""
        fusing = worker(target=fuse_until, args=(stop, frames, K, poses))
        fusing.start()
        try:
            return track_at_camera_rate(frames, K)
        finally:
            stop.set()
            fusing.join()

    results = {"alone": track_at_camera_rate(frames, K)}
    results["fusion in a thread"] = beside(threading.Thread, threading.Event())
    ctx = mp.get_context("fork")  # our fusing thread has ended; the child only fuses
    results["fusion in a process"] = beside(ctx.Process, ctx.Event())
    alone_p95 = np.percentile(results["alone"], 95)
    print(f"{'tracking beside':24s} {'median ms':>10s} {'p95 ms':>8s} {'max ms':>8s}")
    for name, wall in results.items():
        print(
            f"{name:24s} {np.median(wall):10.1f} {np.percentile(wall, 95):8.1f} {wall.max():8.0f}"
        )
    ratio = np.percentile(results["fusion in a process"], 95) / alone_p95
    print(
        f"p95 beside fusion in a process / alone: {ratio:.2f} (target <= "
        f"{TARGET_P95_RATIO:g}): {'PASS' if ratio <= TARGET_P95_RATIO else 'FAIL'}"
    )


if __name__ == "__main__":
    main()
