"""``track`` end to end (issue 15: >= 20 frames/s): the whole command, from the interpreter's
start to the last file written (imports, loading, tracking, fusing, the room, the picture).

Each repeat runs ``python -m server track SEQ --out TMP`` twice, in turn: as it ships (frames
read ahead of the tracker and mapped behind it on threads, ``--overlap``) and with every stage
in turn in one thread (``--no-overlap``), the baseline measured in the same sitting, so that a
slower or busier machine shows in both. Both must write the same trajectory (checked).

    python benchmarks/track_rate.py                                   # 7scenes_a, 3 repeats, ~3 min
    python benchmarks/track_rate.py ../shared/data/synthetic_room0 --repeats 5

Prints the figures against the target, appends them to <out>/track_rate.md and writes
<out>/track_rate.json.
"""

from __future__ import annotations

import argparse
import json
import resource
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table

REPO_ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO_ROOT))

from benchmarks.provenance import git_commit, run_heading, utc_stamp  # noqa: E402

TARGET_FPS = 20.0
console = Console()


def run_track(sequence: Path, out: Path, overlap: bool) -> dict:
    """One ``track`` run in a fresh interpreter: wall and CPU seconds, frames, trajectory."""
    cmd = [sys.executable, "-m", "server", "track", str(sequence), "--out", str(out)]
    cmd.append("--overlap" if overlap else "--no-overlap")
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    done = subprocess.run(cmd, cwd=REPO_ROOT, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if done.returncode != 0:
        raise SystemExit(f"{shlex.join(cmd)} failed:\n{done.stdout[-2000:]}\n{done.stderr[-2000:]}")
    out = out / "latest"  # the run's own folder under --out
    summary = json.loads((out / "summary.json").read_text())
    return {
        "wall_s": wall,
        "cpu_s": (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime),
        "frames": summary["frames"],
        "median_track_ms": summary["median_ms"],
        "trajectory": np.loadtxt(out / "trajectory.tum"),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "sequences", nargs="*", type=Path, default=[REPO_ROOT.parent / "shared/data/7scenes_a"]
    )
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", type=Path, default=REPO_ROOT / "benchmarks" / "results")
    args = parser.parse_args()
    stamp = utc_stamp()
    results: dict[str, dict] = {}
    table = Table(title=f"track end to end ({args.repeats} repeats, median)")
    for col in ("sequence", "mode", "frames", "wall s", "CPU s", "frames/s", "target", ""):
        table.add_column(col, justify="right")
    with tempfile.TemporaryDirectory() as tmp:
        for seq in args.sequences:
            runs: dict[str, list[dict]] = {"overlap": [], "in turn": []}
            for r in range(args.repeats):
                for mode in runs:
                    out = Path(tmp) / f"{seq.name}_{mode.replace(' ', '_')}_{r}"
                    runs[mode].append(run_track(seq, out, overlap=mode == "overlap"))
                    last = runs[mode][-1]
                    console.print(
                        f"{seq.name} {mode} #{r + 1}: {last['wall_s']:.1f} s wall, "
                        f"{last['frames'] / last['wall_s']:.1f} frames/s"
                    )
            same = all(
                np.array_equal(a["trajectory"], b["trajectory"])
                for a, b in zip(runs["overlap"], runs["in turn"], strict=True)
            )
            entry: dict = {"same_trajectory": same}
            for mode, rs in runs.items():
                wall = float(np.median([x["wall_s"] for x in rs]))
                frames = rs[0]["frames"]
                fps = frames / wall
                entry[mode] = {
                    "wall_s": [round(x["wall_s"], 2) for x in rs],
                    "cpu_s": [round(x["cpu_s"], 2) for x in rs],
                    "median_wall_s": round(wall, 2),
                    "frames": frames,
                    "frames_per_s": round(fps, 1),
                    "median_track_ms": [round(x["median_track_ms"], 1) for x in rs],
                }
                met = fps >= TARGET_FPS if mode == "overlap" else None
                table.add_row(
                    seq.name,
                    mode,
                    str(frames),
                    f"{wall:.1f}",
                    f"{np.median([x['cpu_s'] for x in rs]):.1f}",
                    f"{fps:.1f}",
                    f">= {TARGET_FPS:.0f}" if mode == "overlap" else "(baseline)",
                    "" if met is None else ("✓" if met else "✗"),
                )
            entry["speedup"] = round(
                entry["in turn"]["median_wall_s"] / entry["overlap"]["median_wall_s"], 2
            )
            results[seq.name] = entry
    console.print(table)
    for name, e in results.items():
        console.print(
            f"{name}: overlap {e['speedup']:.2f}x faster than in turn; same trajectory: "
            f"{e['same_trajectory']}"
        )
    args.out.mkdir(parents=True, exist_ok=True)
    lines = [
        *run_heading(stamp),
        "| sequence | mode | frames | median wall s (runs) | frames/s | target |",
        "|---|---|---:|---|---:|---|",
    ]
    for name, e in results.items():
        for mode in ("overlap", "in turn"):
            m = e[mode]
            runs_s = ", ".join(f"{w:.1f}" for w in m["wall_s"])
            target = (
                f">= {TARGET_FPS:.0f} {'✓' if m['frames_per_s'] >= TARGET_FPS else '✗'}"
                if mode == "overlap"
                else "baseline"
            )
            lines.append(
                f"| {name} | {mode} | {m['frames']} | {m['median_wall_s']:.1f} ({runs_s}) | "
                f"{m['frames_per_s']:.1f} | {target} |"
            )
        lines.append(
            f"\n{name}: {e['speedup']:.2f}x; the same trajectory both ways: {e['same_trajectory']}"
        )
    with open(args.out / "track_rate.md", "a") as f:
        f.write("\n".join(lines) + "\n")
    (args.out / "track_rate.json").write_text(
        json.dumps({"commit": git_commit(), "date": stamp, "results": results}, indent=1)
    )


if __name__ == "__main__":
    main()
