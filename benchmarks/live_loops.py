"""Live loop closure's cost to the phones: the same load with ``registration.loops.live`` off and
on, alternating, each run on a fresh server on loopback.

Per run: the load tester (``server/client/loadtest``) streams the sequence from N phones at F fps
for the run's duration (the sequence played forward and back, so the camera comes back to
places it saw); the latency percentiles and the captured frames without a pose are set beside
capacity's target (p95 <= 100 ms, < 5 % without a pose; ``benchmarks/capacity.py``), with the
server's CPU per processed frame (its whole process tree, as capacity measures it) and what each
session's loop closure did (its status at the end: keyframes, loops found, corrections, map
rebuilds, look-up CPU per keyframe, the last rebuild's wall time and keyframes).

    python benchmarks/live_loops.py [SEQUENCE] [--sessions 1 2] [--fps 15] [--duration 120] \\
        [--repeats 1]

Appends the table to ``results/live_loops.md`` and writes ``results/live_loops.json``. Run it
on a quiet machine: off and on alternate within one sitting, so both see the same machine.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from rich.console import Console  # noqa: E402
from rich.table import Table  # noqa: E402

from benchmarks.capacity import (  # noqa: E402
    TARGET,
    TreeSampler,
    meets,
    server_cpu_figures,
    server_environment,
    wait_until_settled,
)
from benchmarks.provenance import run_heading, utc_stamp  # noqa: E402
from server.client.loadtest import EncodedSequence, LoadTestConfig, run_loadtest  # noqa: E402
from server.client.server_process import ServerProcess  # noqa: E402
from server.datasets import open_dataset  # noqa: E402

console = Console(width=None if sys.stdout.isatty() else 160)


def run_once(
    seq: EncodedSequence, sessions: int, fps: float, duration_s: float, loops: bool
) -> dict:
    """One fresh server with live loop closure ``loops`` (on or off), N phones streaming."""
    env = {
        **server_environment(sessions + 1),
        "DRONESIM_REGISTRATION__LOOPS__LIVE": "true" if loops else "false",
    }
    with tempfile.TemporaryDirectory() as tmp:
        server = ServerProcess(Path(tmp) / "data", env, Path(tmp) / "server.log")
        try:
            wait_until_settled(server.pid)
            cfg = LoadTestConfig(
                url=server.url,
                sessions=sessions,
                fps=fps,
                duration_s=duration_s,
                client_name="live_loops",
            )
            label = f"{sessions} x {fps:g} fps, loops {'on' if loops else 'off'}"
            with console.status(f"{label}, {duration_s:g} s ..."):
                with TreeSampler(server.pid) as sampler:
                    report = asyncio.run(run_loadtest(seq, cfg))
        finally:
            server.terminate()
    t = report["total"]
    cpu = sampler.summary()
    cpu.update(server_cpu_figures(cpu["cpu_s"], cpu["wall_s"], t["processed"], 0.0))
    statuses = [(s.get("server_status") or {}).get("loops") or {} for s in report["sessions"]]
    row = {
        "sessions": sessions,
        "fps": fps,
        "duration_s": duration_s,
        "loops": loops,
        **{k: t["latency"][k] for k in ("p50_ms", "p95_ms", "p99_ms", "max_ms")},
        "drop_rate": t["drop_rate"],
        "processed": t["processed"],
        "errors": t["errors"],
        "failures": t["failures"],
        "server_cores": cpu["cores"],
        "cpu_ms_per_frame": cpu["cpu_ms_per_frame"],
        "loop_status": statuses,
    }
    row["meets"] = meets(row)
    return row


def _sum(row: dict, key: str) -> float:
    return sum(float(s.get(key) or 0.0) for s in row["loop_status"])


def _worst(row: dict, key: str) -> float | None:
    values = [s[key] for s in row["loop_status"] if s.get(key) is not None]
    return max(values) if values else None


def _cell(value: float | None, pattern: str = "{:.0f}") -> str:
    return "-" if value is None else pattern.format(value)


COLUMNS = [
    "phones x fps",
    "loops",
    "p50 / p95 / p99 / max ms",
    f"no pose (target < {100 * TARGET['drop_rate']:.0f} %)",
    f"meets p95 <= {TARGET['p95_ms']:.0f} ms and no pose",
    "server CPU ms/frame",
    "keyframes",
    "loops found",
    "map rebuilds (skipped)",
    "look-up CPU ms/keyframe (worst session)",
    "last rebuild ms (keyframes)",
    "rebuilds' CPU s, all",
]


def cells(row: dict) -> list[str]:
    rebuild_ms = _worst(row, "last_rebuild_ms")
    rebuild_kf = _worst(row, "last_rebuild_keyframes")
    return [
        f"{row['sessions']} x {row['fps']:g}",
        "on" if row["loops"] else "off",
        " / ".join(_cell(row[k]) for k in ("p50_ms", "p95_ms", "p99_ms", "max_ms")),
        f"{100 * row['drop_rate']:.1f} %",
        "yes" if row["meets"] else "no",
        _cell(row["cpu_ms_per_frame"]),
        f"{_sum(row, 'keyframes'):.0f}" if row["loops"] else "-",
        f"{_sum(row, 'found'):.0f}" if row["loops"] else "-",
        f"{_sum(row, 'rebuilds'):.0f} ({_sum(row, 'rebuilds_skipped'):.0f})"
        if row["loops"]
        else "-",
        _cell(_worst(row, "lookup_cpu_ms")),
        "-" if rebuild_ms is None else f"{rebuild_ms:.0f} ({rebuild_kf:.0f})",
        f"{_sum(row, 'rebuilds_cpu_ms') / 1e3:.1f}" if row["loops"] else "-",
    ]


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "sequence", nargs="?", default=str(REPO.parent / "shared" / "data" / "7scenes_a")
    )
    parser.add_argument("--sessions", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--fps", type=float, default=15.0)
    parser.add_argument("--duration", type=float, default=120.0, help="seconds per run")
    parser.add_argument("--repeats", type=int, default=1, help="off/on pairs per phone count")
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results")
    args = parser.parse_args()

    dataset = open_dataset(args.sequence)
    with console.status(f"encoding {dataset.name} ..."):
        seq = EncodedSequence.from_dataset(dataset)
    rows = []
    for sessions in args.sessions:
        for repeat in range(args.repeats):
            # Alternate which goes first, so that a machine growing busier favours neither.
            for loops in (False, True) if repeat % 2 == 0 else (True, False):
                rows.append(run_once(seq, sessions, args.fps, args.duration, loops))
                console.print(" | ".join(cells(rows[-1])))

    table = Table(*COLUMNS, title=f"live loop closure, {dataset.name}, {args.duration:g} s runs")
    for row in rows:
        table.add_row(*cells(row))
    console.print(table)

    args.out.mkdir(parents=True, exist_ok=True)
    lines = run_heading(utc_stamp(), f", {dataset.name}, {args.duration:g} s per run")
    lines += ["| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    lines += ["| " + " | ".join(cells(row)) + " |" for row in rows]
    with (args.out / "live_loops.md").open("a") as f:
        f.write("\n".join(lines) + "\n")
    (args.out / "live_loops.json").write_text(json.dumps(rows, indent=1))
    console.print(f"appended to {args.out / 'live_loops.md'}")


if __name__ == "__main__":
    main()
