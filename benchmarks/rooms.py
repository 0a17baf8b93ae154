"""Rooms benchmark (issue 15, item 3): map a room, come back later, relocalise into it.

7scenes_a is cut in two: frames 0-299 are tracked and saved as a room (as ``track --out A``
does), frames 350-599 are relocalised into it by place recognition and tracked in its frame (as
``track --start 350 --out B --room A``). One SE(3) alignment over both parts' trajectories against
the ground truth gives the ATE, compared with tracking all 600 frames in one go.

    python benchmarks/rooms.py                       # ~2 min on 2 cores
    python benchmarks/rooms.py --room-frames 0 300 --return-frames 350 600 --out /tmp/rooms

Also measured: the room's size on disk and per minute of mapping, save and load times, the
relocalisation time, and the database look-up (the voting candidates then verification) against
verifying every keyframe, on every 10th frame of the second part. Prints targets and figures
side by side, appends them to <out>/rooms.md, and keeps the case's entry in <out>/rooms.json
(keyed by sequence and frame ranges, e.g. ``7scenes_a 0-300 350-600``; other cases' entries stay).

The ATE is only a pass when the second part was placed in the room: a return never relocalised
leaves the first part alone in the alignment, which says nothing about coming back.
"""

from __future__ import annotations

import os

# One thread everywhere, as the registration benchmark, set before numpy/OpenCV/Open3D start.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402
import open3d as o3d  # noqa: E402
from rich.console import Console  # noqa: E402
from rich.table import Table  # noqa: E402

REPO_ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO_ROOT))

from benchmarks.provenance import git_commit, run_heading, utc_stamp  # noqa: E402
from server.datasets import open_dataset  # noqa: E402
from server.evaluation.metrics import evaluate  # noqa: E402
from server.evaluation.trajectory import Trajectory  # noqa: E402
from server.geometry import invert, rotation_angle_deg  # noqa: E402
from server.pipeline import ground_truth_pose_at, run_odometry  # noqa: E402
from server.registration.calibration import ColourToDepth  # noqa: E402
from server.registration.config import RegistrationConfig  # noqa: E402
from server.registration.place import describe_place  # noqa: E402
from server.registration.preprocess import clean_depth, to_grey  # noqa: E402
from server.registration.verify import find_place, verify_place  # noqa: E402
from server.rooms import load_room, save_room  # noqa: E402

console = Console()
ATE_FACTOR = 1.3  # target: both parts within this factor of the one-go ATE
RELOCALISE_WITHIN = 15  # frames


def lookup_study(room, ds, frames: range, cfg: RegistrationConfig) -> dict:
    """The database's voting look-up then verification of its candidates, against verifying
    every keyframe (the best by inliers): ms per query and how often both find a place."""
    db = room.database()
    vote_ms, all_ms, found_vote, found_all, same = [], [], 0, 0, 0
    # Colour registered to depth as track does where frames come in (estimated once).
    to_depth = ColourToDepth(ds.intrinsics, cfg.depth, not ds.depth_registered)
    for i in frames:
        f = ds[i]
        colour = to_depth(f.colour, f.depth)
        q = describe_place(
            to_grey(colour), clean_depth(f.depth, cfg.depth), ds.intrinsics, cfg.place, cfg.depth
        )
        t = time.perf_counter()
        a = find_place(db, q, ds.intrinsics, cfg.place, cfg.solver, cfg.depth)
        vote_ms.append((time.perf_counter() - t) * 1e3)
        t = time.perf_counter()
        best = None
        for e in db.entries:
            m = verify_place(
                e.features, q, ds.intrinsics, cfg.place, cfg.solver, cfg.depth, e.keyframe_id
            )
            if m is not None and (best is None or m.inliers > best.inliers):
                best = m
        all_ms.append((time.perf_counter() - t) * 1e3)
        found_vote += a is not None
        found_all += best is not None
        same += a is not None and best is not None and a.keyframe_id == best.keyframe_id
    return {
        "queries": len(frames),
        "keyframes": len(db),
        "vote_then_verify_ms_median": float(np.median(vote_ms)),
        "verify_all_ms_median": float(np.median(all_ms)),
        "found_vote": found_vote,
        "found_verify_all": found_all,
        "same_keyframe": same,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "sequence", nargs="?", default=str(REPO_ROOT.parent / "shared/data/7scenes_a")
    )
    parser.add_argument("--room-frames", nargs=2, type=int, default=(0, 300), metavar=("A", "B"))
    parser.add_argument(
        "--return-frames", nargs=2, type=int, default=(350, 600), metavar=("A", "B")
    )
    parser.add_argument("--out", type=Path, default=REPO_ROOT / "benchmarks" / "results")
    args = parser.parse_args()
    cv2.setNumThreads(1)
    o3d.utility.set_max_threads(1)
    cfg = RegistrationConfig()
    ds = open_dataset(args.sequence)
    (a0, a1), (b0, b1) = args.room_frames, args.return_frames

    t = time.perf_counter()
    whole = run_odometry(ds, cfg, max_frames=b1, progress=True)
    whole_s = time.perf_counter() - t
    assert whole.metrics is not None, "the sequence needs ground truth"

    part1 = run_odometry(ds, cfg, max_frames=a1 - a0, start=a0, progress=True)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "room"
        t = time.perf_counter()
        sizes = save_room(part1.room, folder)
        save_s = time.perf_counter() - t
        t = time.perf_counter()
        room = load_room(folder, cfg)
        load_s = time.perf_counter() - t
    room_keyframes = len(room.keyframes)
    lookup = lookup_study(room, ds, range(b0, b1, 10), cfg)
    t = time.perf_counter()
    part2 = run_odometry(ds, cfg, max_frames=b1 - b0, start=b0, room=room, progress=True)
    part2_s = time.perf_counter() - t
    found = part2.summary["relocalisation"]

    both = Trajectory(
        np.concatenate([part1.trajectory.timestamps, part2.trajectory.timestamps]),
        np.concatenate([part1.trajectory.poses, part2.trajectory.poses]),
    )
    assert ds.ground_truth is not None
    ate_both = evaluate(ds.ground_truth, both)["ate_rmse_m"]
    ate_whole = whole.metrics["ate_rmse_m"]
    placed = len(part2.trajectory.timestamps)  # return frames with a pose in the room's frame
    # How far the return starts from where the room's part ended (ground truth): a return that
    # starts where the room left off is the easy case.
    start_off = start_offset(ds, a1 - 1, b0)
    seconds = (a1 - a0) / 30.0  # the sequences' nominal 30 Hz
    room_bytes = sum(sizes.values())
    rows = [
        (
            "ATE, both parts, one alignment",
            f"{ate_both * 100:.2f} cm"
            if placed
            else f"- (part 2 never placed; part 1 alone {ate_both * 100:.2f} cm)",
            f"<= {ATE_FACTOR} x {ate_whole * 100:.2f} = {ATE_FACTOR * ate_whole * 100:.2f} cm",
            placed > 0 and ate_both <= ATE_FACTOR * ate_whole,
        ),
        ("return frames placed", f"{placed} of {b1 - b0}", "", None),
        ("return starts off the room's last frame", "unknown (no ground truth there)"
         if start_off is None else f"{start_off[0]:.2f} m, {start_off[1]:.0f} deg", "", None),
        (
            "relocalised at frame",
            f"{found['frame']} (sequence frame {found.get('sequence_frame')})"
            if found["relocalised"]
            else "never",
            f"< {RELOCALISE_WITHIN}",
            found["relocalised"] and found["frame"] < RELOCALISE_WITHIN,
        ),
        ("relocalisation time", f"{found.get('ms', float('nan')):.0f} ms "
         f"({found.get('total_ms', float('nan')):.0f} ms over all attempts)", "", None),
        ("room on disk", f"{room_bytes / 1e6:.1f} MB ({room_keyframes} keyframes: "
         f"{sizes['keyframes'] / 1e6:.1f} MB images + features, map {sizes['map'] / 1e6:.1f} MB)",
         "", None),
        ("per minute of mapping", f"{room_bytes / 1e6 / seconds * 60:.0f} MB "
         f"({room_keyframes / seconds * 60:.0f} keyframes)", "", None),
        ("save / load", f"{save_s:.1f} s / {load_s:.1f} s", "", None),
        ("look-up: vote + verify 3 / verify all",
         f"{lookup['vote_then_verify_ms_median']:.0f} / {lookup['verify_all_ms_median']:.0f} ms, "
         f"found {lookup['found_vote']} / {lookup['found_verify_all']} of {lookup['queries']}, "
         f"same keyframe {lookup['same_keyframe']}", "", None),
        ("ATE part 2 alone (aligned)", f"{part2.metrics['ate_rmse_m'] * 100:.2f} cm"
         if part2.metrics else "-", "", None),
        ("time: whole / part 2", f"{whole_s:.0f} s / {part2_s:.0f} s", "", None),
    ]  # fmt: skip
    table = Table(title=f"rooms: {ds.name} {a0}-{a1 - 1} as the room, {b0}-{b1 - 1} return")
    for col in ("figure", "measured", "target", ""):
        table.add_column(col)
    for name, value, target, met in rows:
        table.add_row(name, value, target, "" if met is None else ("✓" if met else "✗"))
    console.print(table)

    args.out.mkdir(parents=True, exist_ok=True)
    stamp = utc_stamp()
    lines = [
        *run_heading(stamp, ", one thread (the machine may have been shared)"),
        "| figure | measured | target | |",
        "|---|---|---|---|",
        *(
            f"| {n} | {v} | {t} | {'' if m is None else ('✓' if m else '✗')} |"
            for n, v, t, m in rows
        ),
    ]
    with open(args.out / "rooms.md", "a") as f:
        f.write("\n".join(lines) + "\n")
    result = {
        "sequence": str(ds.path),
        "return_frames_placed": placed,
        "return_start_offset_m_deg": start_off,
        "room_frames": [a0, a1],
        "return_frames": [b0, b1],
        "ate_both_m": ate_both,
        "ate_whole_m": ate_whole,
        "relocalisation": found,
        "room_bytes": sizes,
        "room_keyframes": room_keyframes,
        "save_s": save_s,
        "load_s": load_s,
        "lookup": lookup,
        "commit": git_commit(),
        "date": stamp,
    }
    path = args.out / "rooms.json"
    results = json.loads(path.read_text()) if path.is_file() else {}
    results[case_key(ds.name, (a0, a1), (b0, b1))] = result
    path.write_text(json.dumps(results, indent=1))


def start_offset(ds, last: int, first: int) -> tuple[float, float] | None:
    """(metres, degrees) between the ground-truth poses of frames ``last`` and ``first``."""
    T_a = ground_truth_pose_at(ds, float(ds.timestamps[last]))
    T_b = ground_truth_pose_at(ds, float(ds.timestamps[first]))
    if T_a is None or T_b is None:
        return None
    T = invert(T_a) @ T_b
    return float(np.linalg.norm(T[:3, 3])), rotation_angle_deg(T)


def case_key(sequence: str, room_frames, return_frames) -> str:
    """The rooms.json key of one case: sequence name and both frame ranges (end excluded)."""
    (a0, a1), (b0, b1) = room_frames, return_frames
    return f"{sequence} {a0}-{a1} {b0}-{b1}"


if __name__ == "__main__":
    main()
