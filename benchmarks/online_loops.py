"""Online loop closure's costs (server/sessions/runtime/loop_closing.py,
server/registration/loops.py): what a live session's loop thread spends per keyframe (its cloud,
odometry edge, place lookup and verification), per pose-graph optimisation (over the real keyframes,
and over a few hundred), and what its mapper spends re-fusing N keyframes from their files after a
loop.

A sequence is played forward then back (server/datasets/there_and_back.py), tracked offline as
a live session tracks it, its keyframes written as a session's room writes them; then the loop
closer takes them in order, as the loop thread does. For the large graph the keyframe list is
gone round again and again (ids going on), so that every round closes loops with the earlier
ones.

    python benchmarks/online_loops.py                                   # ~2 min on 2 cores
    python benchmarks/online_loops.py ../shared/data/synthetic_room0 --frames 100 --nodes 300

Prints the figures and appends them to benchmarks/results/online_loops.md.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import datetime  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402
import open3d as o3d  # noqa: E402

REPO_ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO_ROOT))

from server.datasets import open_dataset  # noqa: E402
from server.datasets.there_and_back import ThereAndBack  # noqa: E402
from server.mapping.config import MappingConfig  # noqa: E402
from server.registration import Tracker  # noqa: E402
from server.registration.config import RegistrationConfig  # noqa: E402
from server.registration.loops import LoopCloser  # noqa: E402
from server.registration.preprocess import clean_depth  # noqa: E402
from server.rooms.room import room_keyframe, write_keyframe  # noqa: E402
from server.sessions.processes.mapper import Mapper  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "sequence", nargs="?", default=str(REPO_ROOT.parent / "shared/data/synthetic_room0")
    )
    ap.add_argument("--frames", type=int, default=100, help="played forward, then back")
    ap.add_argument("--nodes", type=int, default=300, help="keyframes of the large graph")
    ap.add_argument("--min-separation", type=int, default=8)
    args = ap.parse_args()
    cv2.setNumThreads(1)
    o3d.utility.set_max_threads(1)

    ds = ThereAndBack(open_dataset(Path(args.sequence)), args.frames)
    cfg = RegistrationConfig().with_overrides(loops={"min_separation": args.min_separation})
    K = ds.intrinsics
    tracker = Tracker(K, cfg)
    keyframes = []
    with tempfile.TemporaryDirectory() as tmp:
        room = Path(tmp)
        for i in range(len(ds)):
            f = ds[i]
            r = tracker.track(f.colour, f.depth)
            tracker.update_keyframe()
            if r.new_keyframe:
                kf = room_keyframe(r.keyframe_id, i, r.T_world_camera, f.colour, f.depth, K, cfg)
                write_keyframe(room, kf)
                keyframes.append((kf, clean_depth(f.depth, cfg.depth)))

        # 1. The loop thread's work per keyframe, and per optimisation, over the real keyframes.
        closer = LoopCloser(K, cfg)
        lookup_ms, optimise_ms = [], []
        for kf, depth in keyframes:
            c0 = time.thread_time()
            loop = closer.add_keyframe(kf.id, kf.T_world_keyframe, kf.place, depth)
            lookup_ms.append((time.thread_time() - c0) * 1e3)
            if loop is not None:
                c0 = time.thread_time()
                closer.optimise()
                optimise_ms.append((time.thread_time() - c0) * 1e3)

        # 2. An optimisation over a few hundred keyframes: round and round the same keyframes.
        big = LoopCloser(K, cfg)
        n, big_lookup = 0, []
        while n < args.nodes:
            for kf, depth in keyframes:
                T = kf.T_world_keyframe
                c0 = time.thread_time()
                big.add_keyframe(n, T, kf.place, depth)
                big_lookup.append((time.thread_time() - c0) * 1e3)
                n += 1
                if n >= args.nodes:
                    break
        t0, c0 = time.perf_counter(), time.thread_time()
        big.optimise()
        big_wall, big_cpu = (time.perf_counter() - t0) * 1e3, (time.thread_time() - c0) * 1e3

        # 3. The mapper's rebuild: every keyframe re-read from its file and fused.
        mapper = Mapper(MappingConfig())
        corrected = closer.optimise()
        mapper.rebuild_start(room, [(kf.id, corrected[kf.id]) for kf, _ in keyframes], K)
        t0 = time.perf_counter()
        mapper.rebuild_step(len(keyframes))
        rebuilt = mapper.rebuild_finish((0.1, np.eye(3)))
        rebuild_wall = (time.perf_counter() - t0) * 1e3

    figures = {
        "sequence": f"{ds.name} ({len(ds)} frames)",
        "keyframes": len(keyframes),
        "loops": len(closer.loops),
        "refused": closer.refused,
        "lookup_cpu_ms_per_keyframe": {
            "mean": round(float(np.mean(lookup_ms)), 1),
            "max": round(float(np.max(lookup_ms)), 1),
        },
        "optimise_cpu_ms": [round(v, 2) for v in optimise_ms],
        "large_graph": {
            "nodes": len(big.nodes),
            "loops": len(big.loops),
            "lookup_cpu_ms_mean": round(float(np.mean(big_lookup)), 1),
            "optimise_wall_ms": round(big_wall, 1),
            "optimise_cpu_ms": round(big_cpu, 1),
        },
        "rebuild": {
            "keyframes": rebuilt.keyframes,
            "wall_ms": round(rebuild_wall, 1),
            "cpu_ms": round(rebuilt.cpu_ms, 1),
            "cpu_ms_per_keyframe": round(rebuilt.cpu_ms / max(1, rebuilt.keyframes), 1),
        },
    }
    text = json.dumps(figures, indent=1)
    print(text)
    out = REPO_ROOT / "benchmarks" / "results" / "online_loops.md"
    stamp = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")
    with out.open("a") as f:
        f.write(
            f"\n## {stamp}, {platform.processor() or platform.machine()}, "
            f"{os.cpu_count()} cores\n\n`python benchmarks/online_loops.py "
            f"{' '.join(sys.argv[1:])}`\n\n```json\n{text}\n```\n"
        )


if __name__ == "__main__":
    main()
