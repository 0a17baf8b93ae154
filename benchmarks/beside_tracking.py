"""Tracking latency alone, and beside a session's background work (TSDF fusion, loop closure) in
a thread of the tracking process or in another process.

Why each session's map and loop closer live in processes of their own
(server/sessions/processes/mapper.py, server/sessions/processes/loop_process.py): Open3D's
``VoxelBlockGrid.integrate`` holds the GIL for its whole call, and a loop closer's look-ups are
numpy, OpenCV and Open3D calls with much Python between them; in a thread of the tracking
process either stalls tracking. Tracks the first frames of a sequence at 15 fps (sleeping out
each frame's period) while, beside it,
- ``fusion``: a fusion runs every 200 ms (Open3D on one thread, niced +10, as the server's
  mapping process);
- ``loops``: every 8th of those frames is a keyframe handed to a ``LoopCloser`` every 500 ms
  (``--keyframe-period``; a hand-held camera's keyframe rate at 15 fps), looked up among
  those at least 4 before it, verified, ICP-refined and the graph optimised on each loop (one
  native thread, niced +15, as the server's loop process), the graph started again when the
  keyframes run out;
and prints tracking's median and p95 per case, against the target that the work in another
process costs tracking's p95 at most 20 % over alone (both runs alone, first and last).

    python benchmarks/beside_tracking.py [SEQUENCE] [--frames 150] [--beside fusion loops]
        [--keyframe-period 0.5]
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
from server.registration.config import RegistrationConfig  # noqa: E402
from server.registration.loops import LoopCloser  # noqa: E402
from server.registration.place import describe_place  # noqa: E402
from server.registration.preprocess import clean_depth, to_grey  # noqa: E402
from server.sessions.processes.priority import (  # noqa: E402
    LOOPS_NICE,
    MAPPING_NICE,
    lower_this_threads_priority,
)

FPS, FUSE_PERIOD_S, TARGET_P95_RATIO = 15.0, 0.2, 1.2
KEYFRAME_EVERY = 8
LOOPS = RegistrationConfig().with_overrides(loops={"min_separation": 4})


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


def close_loops_until(stop, keyframes: list, K, period_s: float) -> None:
    """Hand ``keyframes`` (id, T_world_keyframe, place features, depth) to a loop closer, one
    every ``period_s``, optimising on each loop found, until ``stop``."""
    lower_this_threads_priority(LOOPS_NICE)
    o3d.utility.set_max_threads(1)
    cv2.setNumThreads(1)
    closer, i = LoopCloser(K, LOOPS), 0
    while not stop.is_set():
        if i == len(keyframes):
            closer, i = LoopCloser(K, LOOPS), 0
        if closer.add_keyframe(*keyframes[i]) is not None:
            closer.optimise()
        i += 1
        time.sleep(period_s)


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
    parser.add_argument("--beside", nargs="+", choices=("fusion", "loops"), default=None)
    parser.add_argument("--keyframe-period", type=float, default=0.5, help="seconds")
    args = parser.parse_args()
    work = args.beside or ["fusion", "loops"]
    dataset = open_dataset(args.sequence)
    # In memory first: loading from disk in the loops would change the pace being measured.
    frames = [dataset[i] for i in range(min(args.frames, len(dataset)))]
    K, poses = dataset.intrinsics, dataset.ground_truth.poses
    keyframes = []
    for i in range(0, len(frames), KEYFRAME_EVERY):
        depth = clean_depth(frames[i].depth, LOOPS.depth)
        place = describe_place(to_grey(frames[i].colour), depth, K, LOOPS.place, LOOPS.depth)
        keyframes.append((i, poses[i], place, depth))
    cv2.setNumThreads(2)
    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True
    ).stdout.strip()
    print(
        f"{dataset.name}, {len(frames)} frames at {FPS:g} fps; fusion: one every "
        f"{FUSE_PERIOD_S * 1e3:.0f} ms; loops: a keyframe every {args.keyframe_period * 1e3:.0f} "
        f"ms ({len(keyframes)} keyframes, round again); commit {commit}"
    )
    targets = {
        "fusion": (fuse_until, (frames, K, poses)),
        "loops": (close_loops_until, (keyframes, K, args.keyframe_period)),
    }

    def beside(name: str, worker, stop) -> np.ndarray:
        """Tracking timed while ``worker`` (a Thread or Process class) does ``name``'s work
        until ``stop``."""
        target, target_args = targets[name]
        other = worker(target=target, args=(stop, *target_args))
        other.start()
        try:
            return track_at_camera_rate(frames, K)
        finally:
            stop.set()
            other.join()

    track_at_camera_rate(frames[:30], K)  # warm-up: first calls pay for caches and pages
    results = {"alone": track_at_camera_rate(frames, K)}
    ctx = mp.get_context("fork")  # each thread beside has ended first; the child only works
    for name in work:
        results[f"{name} in a thread"] = beside(name, threading.Thread, threading.Event())
        results[f"{name} in a process"] = beside(name, ctx.Process, ctx.Event())
    # Alone again at the end: the machine's own drift over the run, beside the baseline.
    results["alone, again"] = track_at_camera_rate(frames, K)
    alone_p95 = np.percentile(np.concatenate([results["alone"], results["alone, again"]]), 95)
    print(f"{'tracking beside':24s} {'median ms':>10s} {'p95 ms':>8s} {'max ms':>8s}")
    for name, wall in results.items():
        print(
            f"{name:24s} {np.median(wall):10.1f} {np.percentile(wall, 95):8.1f} {wall.max():8.0f}"
        )
    for name in work:
        ratio = np.percentile(results[f"{name} in a process"], 95) / alone_p95
        in_thread = np.percentile(results[f"{name} in a thread"], 95) / alone_p95
        print(
            f"p95 beside {name} in a process / alone: {ratio:.2f} (target <= "
            f"{TARGET_P95_RATIO:g}): {'PASS' if ratio <= TARGET_P95_RATIO else 'FAIL'}; "
            f"in a thread: {in_thread:.2f}"
        )


if __name__ == "__main__":
    main()
