"""Flight-map feed benchmark: CPU per fused frame of the full occupancy + distance-field rebuild
(the session's 3 s timer) against the incremental feed (``TSDFMap.occupancy_update`` +
``FlightMap.update_region``, what ``Flight.feed_from_map`` does after each fused frame).

Frames ``--start``.. of a sequence, every ``--every``-th, are fused into a TSDF map at their
ground-truth poses; the first ``--warmup`` of them build the map untimed. Then, after every
further fused frame, in one process on one thread, on the same map:

- full: ``occupancy`` (whole grid), then ``FlightMap.update`` of a persistent map with it (its
  own windowed update, rebuilding when the change is over half the grid) — today's work per 3 s;
- incremental: ``occupancy_update`` (the box the frame can have changed) and ``update_region``
  of another persistent map — the work the feed does per fused frame;
- incremental, merged: the same boxes merged over ``--merge`` frames (as ``Flight`` coalesces
  them while its thread is busy), applied once.

Every frame the incremental map's field is checked against a fresh rebuild of the full grid
(exact equality). CPU time (``time.process_time``) per call, in ms.

    python benchmarks/flight_map_update.py                       # 7scenes_a
    python benchmarks/flight_map_update.py ../shared/data/synthetic_room0 --every 3
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # one core: numpy must not fan out

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import open3d as o3d  # noqa: E402

REPO_ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO_ROOT))

from server.datasets import open_dataset  # noqa: E402
from server.evaluation.plots import top_view_basis, up_direction  # noqa: E402
from server.mapping.tsdf import TSDFMap  # noqa: E402
from server.pipeline import ground_truth_pose_at  # noqa: E402
from server.simulation.config import SimulationConfig  # noqa: E402
from server.simulation.flight_map import FlightMap  # noqa: E402
from server.simulation.map_regions import Region  # noqa: E402

DATA = REPO_ROOT.parent / "shared" / "data"


def cpu_ms(call):
    start = time.process_time()
    out = call()
    return out, (time.process_time() - start) * 1e3


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("sequence", nargs="?", type=Path, default=DATA / "7scenes_a")
    parser.add_argument("--start", type=int, default=0)
    parser.add_argument("--every", type=int, default=3, help="fuse every n-th frame")
    parser.add_argument("--warmup", type=int, default=60, help="fused frames before timing")
    parser.add_argument("--frames", type=int, default=30, help="fused frames timed")
    parser.add_argument("--merge", type=int, default=5, help="frames merged per apply")
    args = parser.parse_args(argv)
    o3d.utility.set_max_threads(1) if hasattr(o3d.utility, "set_max_threads") else None

    config = SimulationConfig()
    voxel = config.voxel_m
    dataset = open_dataset(args.sequence)
    indices = list(range(args.start, len(dataset), args.every))[: args.warmup + args.frames]
    poses = [ground_truth_pose_at(dataset, dataset[i].timestamp) for i in indices]
    up = up_direction(np.array([T for T in poses if T is not None]))
    R = np.vstack([top_view_basis(up), up])  # flight frame: z up, as the planning benchmark

    tsdf = TSDFMap()
    full_map = FlightMap(voxel, config.unknown_is_free)
    feed_map = FlightMap(voxel, config.unknown_is_free)
    merged_map = FlightMap(voxel, config.unknown_is_free)
    rows = {
        k: []
        for k in (
            "occupancy",
            "full_update",
            "rebuild",
            "occupancy_update",
            "update_region",
            "merged_update",
            "box_share",
            "changed_cells",
        )
    }
    pending: Region | None = None
    for n, (i, T) in enumerate(zip(indices, poses, strict=True)):
        if T is None:
            continue
        frame = dataset[i]
        tsdf.integrate(frame.colour, frame.depth, dataset.intrinsics, T)
        timed = n >= args.warmup
        grid, t_occ = cpu_ms(lambda: tsdf.occupancy(voxel, R))
        box, t_box = cpu_ms(lambda: tsdf.occupancy_update(voxel, R))
        if not timed:  # build the maps as a session would have by now
            full_map.update(*grid)
            if box is not None:
                feed_map.update_region(*box)
                merged_map.update_region(*box)
            continue
        before = feed_map.blocked.copy() if feed_map.shape == grid[1].shape else None
        _, t_full = cpu_ms(lambda g=grid: full_map.update(*g))
        _, t_rebuild = cpu_ms(lambda g=grid: FlightMap(voxel, config.unknown_is_free).update(*g))
        t_region = 0.0
        if box is not None:
            _, t_region = cpu_ms(lambda b=box: feed_map.update_region(*b))
            region = Region.whole(*box)
            pending = region if pending is None else pending.merged(region, voxel)
            rows["box_share"].append(box[1].size / grid[1].size)
        if (n - args.warmup) % args.merge == args.merge - 1 and pending is not None:
            _, t_merged = cpu_ms(
                lambda p=pending: merged_map.update_region(
                    p.origin, p.occupied, p.observed, p.written
                )
            )
            rows["merged_update"].append(t_merged)
            pending = None
        if before is not None and feed_map.shape == before.shape:
            rows["changed_cells"].append(int((feed_map.blocked != before).sum()))
        check = FlightMap(voxel, config.unknown_is_free)
        check.update(*grid)
        assert np.array_equal(check.esdf, feed_map.esdf), f"frame {i}: feed differs from rebuild"
        for key, value in (
            ("occupancy", t_occ),
            ("full_update", t_full),
            ("rebuild", t_rebuild),
            ("occupancy_update", t_box),
            ("update_region", t_region),
        ):
            rows[key].append(value)

    def med(key):
        return float(np.median(rows[key])) if rows[key] else float("nan")

    shape = full_map.shape
    print(
        f"{args.sequence.name}: frames {indices[args.warmup]}..{indices[-1]} every "
        f"{args.every} (after {args.warmup} fused), grid {shape[0]}x{shape[1]}x{shape[2]} "
        f"cells of {voxel} m; medians of {len(rows['occupancy'])} frames, CPU ms, one thread"
    )
    print(
        f"  dirty box / whole grid: {100 * med('box_share'):.0f} %; cells changed per "
        f"frame: {med('changed_cells'):.0f}"
    )
    print(f"  {'step':<34}{'full (today)':>14}{'incremental':>14}")
    print(
        f"  {'occupancy extraction':<34}{med('occupancy'):>14.1f}{med('occupancy_update'):>14.1f}"
    )
    print(
        f"  {'flight map update (1 frame)':<34}{med('full_update'):>14.1f}"
        f"{med('update_region'):>14.1f}"
    )
    print(f"  {'flight map, fresh full rebuild':<34}{med('rebuild'):>14.1f}{'':>14}")
    print(f"  {f'flight map, {args.merge} frames merged':<34}{'':>14}{med('merged_update'):>14.1f}")
    per_frame = med("occupancy_update") + med("update_region")
    today = med("occupancy") + med("full_update")
    print(
        f"  per fused frame, incremental: {per_frame:.1f} ms; per 3 s timer today: {today:.1f} "
        f"ms -> incremental costs less only below {today / max(per_frame, 1e-9) / 3:.2f} fused "
        f"frames/s"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
