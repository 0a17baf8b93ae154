"""Ray on one node against the process workers: the same load on ``serve`` and ``serve --ray
local``, rows alternating between the two in one run, so that both see the same machine.

Per row a fresh server (``ServerProcess``; for Ray ``DRONESIM_RAY=local``: a Ray instance of the
server's own, on 127.0.0.1 only, in a temp dir of the row's own), left to settle, then the load
tester (``server/client/loadtest``) in this process: N sessions at F fps for D seconds. Each row
records the poses per second, the send-to-pose latency, the tracker's own time per frame (the
poses' ``timings_ms["track"]``: it grows when something else holds the session's GIL, e.g. a
TSDF fusion in a thread beside it), the server's process-tree CPU, the machine's busy share and
the load average (1 min) before and after the row: the machine may be shared, and the figures
are only comparable within a run. Rows of each (sessions, workers) pair repeat ``--repeats``
times, the order of the kinds of workers reversed on every other repeat.

``--base DIR``: a third kind, ``ray-base``, Ray workers as the code in DIR has them (another copy
of this repository, e.g. before a change: ``git archive HEAD | tar -x -C DIR``), its server
started in DIR (Ray's workers then import DIR's code: the count of Ray mapper processes,
sampled in the server's process tree during each row, tells an actor that fuses in a mapper
process from one that fuses in a thread). A
machine where others work on the checkout: run the script from a copy of it too, so that no
row runs code changed halfway through the run.

    python benchmarks/ray_one_node.py [SEQUENCE] --label after [--sessions 1 2] [--fps 15]
        [--duration 20] [--repeats 2] [--base DIR]

Writes ``benchmarks/results/ray_one_node.json`` (each run under its ``--label``; a run of the
same label replaces it) and ``ray_one_node.md`` (every run in the JSON: its rows, and per
sessions count the medians over the repeats and Ray's tracking p95 over the process workers').
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import platform
import shlex
import statistics
import sys
import tempfile
import threading
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # run from anywhere, installed or not

from capacity import (  # noqa: E402
    TreeSampler,
    scan_tree,
    server_environment,
    wait_until_settled,
)
from provenance import git_commit, utc_stamp  # noqa: E402

from server.client import server_process  # noqa: E402
from server.client.loadtest import EncodedSequence, LoadTestConfig, run_loadtest  # noqa: E402
from server.client.server_process import ServerProcess  # noqa: E402
from server.datasets import open_dataset  # noqa: E402

KINDS = ("process", "ray", "ray-base")
SETTLE_CORES = {"process": 0.1, "ray": 0.35, "ray-base": 0.35}  # Ray's processes never rest


class MapperCount:
    """The most Ray mapper processes (an actor's children) seen at once in the server's process
    tree, sampled every second over a ``with`` block."""

    def __init__(self, root: int) -> None:
        self.root, self.most = root, 0
        self._stop = threading.Event()

    def _count(self) -> int:
        count = 0
        for pid in scan_tree(self.root):
            try:
                line = Path(f"/proc/{pid}/cmdline").read_bytes()
            except OSError:
                continue
            # fresh.fresh_main running mapper_main (before 2026-12-06: actor_host.mapper_child)
            count += b"mapper_child" in line or (b"fresh_main" in line and b"mapper_main" in line)
        return count

    def _run(self) -> None:
        while not self._stop.wait(1.0):
            self.most = max(self.most, self._count())

    def __enter__(self) -> MapperCount:
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()


def run_row(
    kind: str,
    seq: EncodedSequence,
    sessions: int,
    fps: float,
    duration_s: float,
    base: Path | None = None,
) -> dict:
    with tempfile.TemporaryDirectory(prefix="r1n", dir="/tmp") as tmp:
        env = server_environment(sessions + 1)
        if kind.startswith("ray"):
            # Ray's sockets, logs and address file in the row's folder (short: socket paths);
            # no usage report leaves the machine.
            env |= {"DRONESIM_RAY": "local", "RAY_TMPDIR": tmp, "RAY_USAGE_STATS_ENABLED": "0"}
        log = Path(tmp) / "server.log"
        ours = server_process.IMPORT_ROOT
        if kind == "ray-base":  # its server (and so its Ray's workers) in the base tree
            server_process.IMPORT_ROOT = base
        try:
            server = ServerProcess(Path(tmp) / "data", env, log)
        finally:
            server_process.IMPORT_ROOT = ours
        try:
            settle_s = wait_until_settled(server.pid, SETTLE_CORES[kind], window_s=1.0)
            load_before = os.getloadavg()[0]
            cfg = LoadTestConfig(
                url=server.url,
                sessions=sessions,
                fps=fps,
                duration_s=duration_s,
                client_name="ray_one_node",
            )
            with TreeSampler(server.pid) as sampler, MapperCount(server.pid) as mappers:
                report = asyncio.run(run_loadtest(seq, cfg))
            load_after = os.getloadavg()[0]
        finally:
            server.terminate()
        failures = [f for s in report["sessions"] for f in s["failures"]]
        if failures:
            print(f"server log (tail):\n{log.read_text(errors='replace')[-3000:]}")
    t, track = report["total"], report["stages_ms"].get("track", {})
    server_figures = sampler.summary()
    return {
        "kind": kind,
        "sessions": sessions,
        "fps": fps,
        "duration_s": duration_s,
        "poses_per_s": t["processed_fps"],
        "poses_per_s_per_session": t["processed_fps_per_session"],
        "p50_ms": t["latency"]["p50_ms"],
        "p95_ms": t["latency"]["p95_ms"],
        "track_median_ms": track.get("median"),
        "track_p95_ms": track.get("p95"),
        "server_drop_rate": t["server_drop_rate"],
        "drop_rate": t["drop_rate"],
        "server_cores": server_figures["cores"],
        "machine_busy": server_figures["machine_busy"],
        "load_before": load_before,
        "load_after": load_after,
        "settle_s": settle_s,
        "ray_mappers": mappers.most,
        "failures": failures[:10],
        "stages_ms": report["stages_ms"],
    }


def _fmt(value, pattern: str = "{:.0f}") -> str:
    return "-" if value is None else pattern.format(value)


def summary(rows: list[dict]) -> list[dict]:
    """Per sessions count: the medians over the repeats of each kind, and Ray's over the
    process workers' (tracking p95, poses/s)."""
    out = []
    for sessions in sorted({r["sessions"] for r in rows}):
        medians = {}
        for kind in KINDS:
            mine = [r for r in rows if r["sessions"] == sessions and r["kind"] == kind]
            if mine:
                medians[kind] = {
                    k: statistics.median(r[k] for r in mine if r[k] is not None)
                    for k in ("track_p95_ms", "poses_per_s", "p95_ms", "load_before")
                }
        line = {"sessions": sessions, **medians}
        for kind in KINDS[1:]:
            if kind in medians and "process" in medians:
                key = kind.replace("-", "_")
                line[f"{key}_over_process_track_p95"] = (
                    medians[kind]["track_p95_ms"] / medians["process"]["track_p95_ms"]
                )
                line[f"{key}_over_process_poses"] = (
                    medians[kind]["poses_per_s"] / medians["process"]["poses_per_s"]
                )
        out.append(line)
    return out


def markdown(runs: dict) -> str:
    lines = [
        "# Ray on one node against the process workers (`benchmarks/ray_one_node.py`)",
        "",
        "Rows of one run alternate between the kinds of workers, a fresh server each; "
        "compare within a run. **track** is the tracker's own time per frame (the poses' "
        "`timings_ms.track`), **p95 ms** send to pose; load: the 1-minute load average "
        "before / after the row (2 cores: above 2 means other jobs took cores); **Ray mapper "
        "processes**: the most seen at once during the row (0: the actors fused in a thread).",
    ]
    for label, run in runs.items():
        m = run["meta"]
        lines += [
            "",
            f"## {label}: {m['date']}, commit {m['commit']}",
            "",
            f"`{m['command']}`; {m['machine']}, {m['cores']} CPUs; {m['dataset']}, "
            f"{m['frames']} frames. {m.get('note', '')}",
            "",
            "| workers | sessions x fps | poses/s (all) | poses/s per session | p50 ms | p95 ms | "
            "track median ms | track p95 ms | server drops | machine busy | "
            "load | Ray mapper processes |",
            "|---|---|--:|--:|--:|--:|--:|--:|--:|--:|---|--:|",
        ]
        for r in run["rows"]:
            lines.append(
                f"| {r['kind']} | {r['sessions']} x {r['fps']:g} | {r['poses_per_s']:.1f} | "
                f"{r['poses_per_s_per_session']:.1f} | {_fmt(r['p50_ms'])} | "
                f"{_fmt(r['p95_ms'])} | {_fmt(r['track_median_ms'], '{:.1f}')} | "
                f"{_fmt(r['track_p95_ms'], '{:.1f}')} | {100 * r['server_drop_rate']:.1f} % | "
                f"{100 * r['machine_busy']:.0f} % | "
                f"{r['load_before']:.1f} / {r['load_after']:.1f} | "
                f"{r.get('ray_mappers', '-') if r['kind'] != 'process' else '-'} |"
                + (f" failures: {len(r['failures'])}" if r["failures"] else "")
            )
        kinds = [k for k in KINDS if any(k in line for line in run["summary"])]
        lines += [
            "",
            "Medians over the repeats: tracking p95 ms and poses/s (all sessions); each Ray "
            "kind's over the process workers' (1.00: the same).",
            "",
            "| sessions | "
            + " | ".join(f"{k}: track p95, poses/s" for k in kinds)
            + "".join(f" | {k} / process: track p95, poses/s" for k in kinds[1:])
            + " |",
            "|--:|" + "---|" * (2 * len(kinds) - 1),
        ]
        for line in run["summary"]:
            cells = [
                "-"
                if line.get(k) is None
                else f"{line[k]['track_p95_ms']:.1f} ms, {line[k]['poses_per_s']:.1f}"
                for k in kinds
            ]
            for k in kinds[1:]:
                key = k.replace("-", "_")
                cells.append(
                    f"{_fmt(line.get(f'{key}_over_process_track_p95'), '{:.2f}')}, "
                    f"{_fmt(line.get(f'{key}_over_process_poses'), '{:.2f}')}"
                )
            lines.append(f"| {line['sessions']} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "sequence", nargs="?", default=str(REPO.parent / "shared" / "data" / "synthetic_room0")
    )
    parser.add_argument("--label", required=True, help="the run's name in the results")
    parser.add_argument("--note", default="", help="a sentence printed with the run")
    parser.add_argument("--sessions", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--fps", type=float, default=15.0)
    parser.add_argument("--duration", type=float, default=20.0)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--frames", type=int, default=None, help="only the first N frames")
    parser.add_argument("--kinds", nargs="+", choices=KINDS, default=["process", "ray"])
    parser.add_argument(
        "--base", type=Path, default=None, help="a copy of the repository to run ray-base from"
    )
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results")
    args = parser.parse_args()

    if args.base is not None and "ray-base" not in args.kinds:
        args.kinds.append("ray-base")
    if "ray-base" in args.kinds and args.base is None:
        parser.error("ray-base needs --base DIR")
    dataset = open_dataset(args.sequence)
    seq = EncodedSequence.from_dataset(dataset, args.frames)
    meta = {
        "date": utc_stamp(),
        "commit": git_commit(),
        "command": shlex.join(["python", *sys.argv]),
        "machine": platform.platform(),
        "cores": os.cpu_count(),
        "dataset": seq.name,
        "frames": len(seq.frames),
        "note": args.note,
        "base": None if args.base is None else str(args.base),
    }
    rows = []
    for repeat in range(args.repeats):
        for sessions in args.sessions:
            kinds = args.kinds if repeat % 2 == 0 else args.kinds[::-1]
            for kind in kinds:
                row = run_row(kind, seq, sessions, args.fps, args.duration, args.base)
                row["repeat"] = repeat
                rows.append(row)
                print(
                    f"{kind:7s} {sessions} x {args.fps:g}: {row['poses_per_s']:.1f} poses/s, "
                    f"p95 {_fmt(row['p95_ms'])} ms, track p95 "
                    f"{_fmt(row['track_p95_ms'], '{:.1f}')} ms (median "
                    f"{_fmt(row['track_median_ms'], '{:.1f}')}), load {row['load_before']:.1f}"
                    f" / {row['load_after']:.1f}, Ray mappers {row['ray_mappers']}, failures "
                    f"{len(row['failures'])}",
                    flush=True,
                )
    run = {"meta": meta, "rows": rows, "summary": summary(rows)}
    for s in run["summary"]:
        print(json.dumps(s))
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "ray_one_node.json"
    runs = json.loads(path.read_text()) if path.is_file() else {}
    runs[args.label] = run
    path.write_text(json.dumps(runs, indent=1))
    (args.out / "ray_one_node.md").write_text(markdown(runs))
    print(f"wrote {path} and ray_one_node.md")
    return 1 if any(r["failures"] for r in rows) else 0


if __name__ == "__main__":
    sys.exit(main())
