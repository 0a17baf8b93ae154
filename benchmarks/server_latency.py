"""Server latency benchmark: one session replaying a sequence over loopback at 30 and 15 fps.

Starts ``python -m server serve`` in its own process (so the client does not share its GIL),
streams the sequence like a camera (at most two frames in flight; frames captured while busy are
dropped on the client), and prints frame-to-pose latency percentiles, frames processed/dropped
and the server's per-stage times, next to the target (p95 <= 50 ms at 15 fps, 640x480, fusion on).

    python benchmarks/server_latency.py [SEQUENCE] [--frames N] [--fps 30 15]
"""

from __future__ import annotations

import argparse
import asyncio
import datetime
import json
import os
import platform
import sys
import tempfile
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table

from server.client.replay import latency_summary, replay
from server.client.server_process import ServerProcess, environment
from server.datasets import open_dataset

REPO = Path(__file__).resolve().parents[1]
TARGET_P95_MS_AT_15 = 50.0
console = Console()


def run_once(server: ServerProcess, dataset, fps: float, frames: int) -> dict:
    sid, token = server.create_session()
    stats = asyncio.run(
        replay(
            f"{server.ws_url}/ws/sessions/{sid}",
            token,
            dataset,
            fps=fps,
            max_frames=frames,
            client_name="bench",
            preencode=True,
        )
    )
    summary = latency_summary(stats)
    stages: dict[str, list[float]] = {}
    for pose in stats.poses:
        for name, ms in pose["timings_ms"].items():
            stages.setdefault(name, []).append(ms)
    summary["stages_median_ms"] = {k: float(np.median(v)) for k, v in sorted(stages.items())}
    summary["fps"] = fps
    summary["duration_s"] = frames / fps
    summary["processed_fps"] = summary["poses"] / summary["duration_s"]
    return summary


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "sequence", nargs="?", default=str(REPO.parent / "shared" / "data" / "synthetic_room0")
    )
    parser.add_argument("--frames", type=int, default=None, help="frames per run (default: all)")
    parser.add_argument("--fps", type=float, nargs="+", default=[30.0, 15.0])
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results")
    parser.add_argument(
        "--server-env",
        nargs="*",
        default=[],
        metavar="NAME=VALUE",
        help="server settings, e.g. DRONESIM_ALLOCATOR=system",
    )
    args = parser.parse_args()

    dataset = open_dataset(args.sequence)
    frames = len(dataset) if args.frames is None else min(args.frames, len(dataset))
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        server = ServerProcess(Path(tmp), environment(args.server_env))
        try:
            allocator = server.health()["allocator"]
            for fps in args.fps:
                console.print(f"replaying {frames} frames of {dataset.name} at {fps:g} fps ...")
                rows.append(run_once(server, dataset, fps, frames))
        finally:
            server.terminate(timeout_s=60)

    table = Table(
        title=f"server latency, one session, {dataset.name} "
        f"{dataset.intrinsics.width}x{dataset.intrinsics.height}, fusion on"
    )
    for col in (
        "fps",
        "sent",
        "poses",
        "client drop",
        "server drop",
        "errors",
        "p50 ms",
        "p95 ms",
        "p99 ms",
        "target p95",
        "stages (median ms)",
    ):
        table.add_column(col, justify="right")
    for r in rows:
        target = (
            f"<= {TARGET_P95_MS_AT_15:.0f} "
            + ("PASS" if r["p95_ms"] <= TARGET_P95_MS_AT_15 else "FAIL")
            if r["fps"] == 15
            else "-"
        )
        stages = ", ".join(
            f"{k} {v:.1f}"
            for k, v in r["stages_median_ms"].items()
            if not k.startswith("track_") or k == "track_cpu"
        )
        table.add_row(
            f"{r['fps']:g}",
            str(r["sent"]),
            str(r["poses"]),
            str(r["client_dropped"]),
            str(r["server_dropped"]),
            str(r["errors"]),
            f"{r['p50_ms']:.1f}",
            f"{r['p95_ms']:.1f}",
            f"{r['p99_ms']:.1f}",
            target,
            stages,
        )
    console.print(table)
    args.out.mkdir(parents=True, exist_ok=True)
    header = (
        f"\n## {dataset.name}, {datetime.datetime.now():%Y-%m-%d %H:%M}\n\n"
        f"machine: {platform.platform()}, {os.cpu_count()} cores; server on {allocator}; command: "
        f"`python {' '.join(sys.argv)}`\n\n"
    )
    with open(args.out / "server_latency.md", "a") as f:
        f.write(header)
        Console(file=f, width=200, force_terminal=False).print(table)
    (args.out / "server_latency.json").write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
