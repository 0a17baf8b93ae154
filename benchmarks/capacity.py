"""Capacity: how many phones one server holds, with map fusion and the drone simulation on.

Starts ``python -m server serve`` in its own process, then runs the load tester
(``server/client/loadtest.py``) in this process for every combination of sessions (1, 2, 4, 8)
and frame rate (15, 30 fps), one after another, while sampling the server process's CPU and
memory. Writes ``benchmarks/results/capacity.md`` and ``capacity.json``: per row the latency
percentiles, processed fps per session, drop rates (client side, server side, and every captured
frame without a pose), server CPU and RSS, the load tester's own CPU; the target (4 sessions at
15 fps: p95 <= 100 ms and < 5 % of captured frames without a pose) with PASS/FAIL; and what
limits it, computed from the measured CPU per frame and the server's stage timings.

    python benchmarks/capacity.py [SEQUENCE] [--duration 30] [--sessions 1 2 4 8] [--fps 15 30]
    python benchmarks/capacity.py --quick     # smoke run: 5 s per row on 30 frames

The load tester shares the machine with the server (loopback): its CPU share is reported, and
taken off the cores available to the server in the analysis.
"""

from __future__ import annotations

import argparse
import asyncio
import datetime
import json
import os
import platform
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # run from anywhere, installed or not

import numpy as np  # noqa: E402
from rich import box  # noqa: E402
from rich.console import Console  # noqa: E402
from rich.table import Table  # noqa: E402

from server.client.loadtest import EncodedSequence, LoadTestConfig, live_line, run_loadtest  # noqa: E402
from server.client.server_process import ServerProcess, rss_mb  # noqa: E402
from server.datasets import open_dataset  # noqa: E402
from server.settings import Settings  # noqa: E402

TARGET = {"sessions": 4, "fps": 15.0, "p95_ms": 100.0, "drop_rate": 0.05}
console = Console()


# ---- the server and its CPU / memory ------------------------------------------------------------


def server_environment(max_sessions: int) -> dict[str, str]:
    """Settings for the run: room for every session, no create rate limit (one load-test IP
    creates every session)."""
    return {"DRONESIM_MAX_SESSIONS": str(max_sessions), "DRONESIM_CREATE_RATE_PER_MIN": "0"}


class ProcessSampler:
    """CPU time and RSS of one process (all its threads, from /proc), sampled in a background
    thread."""

    def __init__(self, pid: int, every_s: float = 0.5) -> None:
        self.pid, self.every_s = pid, every_s
        self._tick = os.sysconf("SC_CLK_TCK")
        self._stop = threading.Event()
        self._rss: list[float] = []

    def cpu_s(self) -> float:
        fields = Path(f"/proc/{self.pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / self._tick  # utime, stime

    def rss_mb(self) -> float:
        return rss_mb(self.pid)

    def __enter__(self) -> ProcessSampler:
        self._t0, self._cpu0 = time.monotonic(), self.cpu_s()
        self._thread = threading.Thread(target=self._sample, daemon=True)
        self._thread.start()
        return self

    def _sample(self) -> None:
        while not self._stop.wait(self.every_s):
            self._rss.append(self.rss_mb())

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()
        self.wall_s = time.monotonic() - self._t0
        self.cpu_used_s = self.cpu_s() - self._cpu0
        self._rss.append(self.rss_mb())

    def summary(self) -> dict:
        """cpu_percent: of one core (200 % = two cores busy)."""
        return {"cpu_s": self.cpu_used_s, "wall_s": self.wall_s,
                "cpu_percent": 100 * self.cpu_used_s / self.wall_s,
                "rss_max_mb": max(self._rss), "rss_end_mb": self._rss[-1]}


# ---- one row ------------------------------------------------------------------------------------


def run_row(url: str, seq: EncodedSequence, pid: int, sessions: int, fps: float,
            duration_s: float) -> dict:
    cfg = LoadTestConfig(url=url, sessions=sessions, fps=fps, duration_s=duration_s,
                         client_name="capacity")
    with console.status(f"{sessions} x {fps:g} fps ...") as status:
        def show(results, elapsed: float) -> None:
            status.update(f"{sessions} x {fps:g} fps, {elapsed:4.1f}/{duration_s:g} s | "
                          f"{live_line(results, elapsed)}")

        with ProcessSampler(pid) as sampler:
            report = asyncio.run(run_loadtest(seq, cfg, on_progress=show))
    t = report["total"]
    row = {"sessions": sessions, "fps": fps, "duration_s": duration_s,
           **{k: t["latency"][k] for k in ("p50_ms", "p95_ms", "p99_ms")},
           "processed_fps_per_session": t["processed_fps_per_session"],
           "processed_fps": t["processed_fps"],
           **{k: t[k] for k in ("captured", "sent", "processed", "client_dropped",
                                "server_dropped", "client_drop_rate", "server_drop_rate",
                                "drop_rate", "errors", "failures")},
           "server": sampler.summary(),
           "client_cpu_percent": report["client_cpu_percent"],
           "stages_ms": report["stages_ms"],
           "drone_states": sum(s["commands"]["drone_states"] for s in report["sessions"]),
           "failure_messages": [f for s in report["sessions"] for f in s["failures"]][:10]}
    row["server"]["cpu_ms_per_frame"] = (1e3 * row["server"]["cpu_s"] / t["processed"]
                                         if t["processed"] else None)
    if sessions == TARGET["sessions"] and fps == TARGET["fps"]:
        row["target"] = bool(row["p95_ms"] is not None and row["p95_ms"] <= TARGET["p95_ms"]
                             and row["drop_rate"] < TARGET["drop_rate"] and not row["failures"])
    return row


# ---- analysis and report ------------------------------------------------------------------------


def _memory_per_session(rows: list[dict]) -> tuple[float, float] | None:
    """(MB per session, MB base) from a straight line through the rows' peak RSS."""
    sessions = [r["sessions"] for r in rows]
    if len(set(sessions)) < 2:
        return None
    slope, base = np.polyfit(sessions, [r["server"]["rss_max_mb"] for r in rows], 1)
    return float(slope), float(base)


def cpu_model(rows: list[dict]) -> dict:
    """Server cores used = idle + per session x sessions + per frame x processed frames/s, fitted
    over the rows by least squares; when the fit is not meaningful (fewer than 4 rows, or a
    negative term), the all-in CPU per processed frame alone."""
    X = np.array([[1.0, r["sessions"], r["processed"] / r["server"]["wall_s"]] for r in rows])
    y = np.array([r["server"]["cpu_s"] / r["server"]["wall_s"] for r in rows])
    if len(rows) >= 4 and np.linalg.matrix_rank(X) == 3:
        idle, session, frame_s = np.linalg.lstsq(X, y, rcond=None)[0]
        if min(idle, session, frame_s) >= 0:
            return {"fit": True, "idle_cores": float(idle), "session_cores": float(session),
                    "frame_ms": float(frame_s * 1e3)}
    processed = sum(r["processed"] for r in rows)
    frame_ms = 1e3 * sum(r["server"]["cpu_s"] for r in rows) / processed if processed else None
    return {"fit": False, "idle_cores": 0.0, "session_cores": 0.0, "frame_ms": frame_ms}


def what_limits_it(rows: list[dict], cores: int, load_before: float) -> str:
    """A paragraph from the measured server CPU, stage timings and memory."""
    model = cpu_model(rows)
    if not model["frame_ms"]:
        return "No frame was processed: nothing to analyse (see the failures)."
    idle, session, frame_ms = model["idle_cores"], model["session_cores"], model["frame_ms"]
    n, fps = TARGET["sessions"], TARGET["fps"]
    calm = min(rows, key=lambda r: (r["sessions"], r["fps"]))  # the least contended row
    decode = calm["stages_ms"].get("decode", {}).get("median", 0.0)
    track = calm["stages_ms"].get("track", {}).get("median", 0.0)
    client = float(np.median([r["client_cpu_percent"] for r in rows])) / 100
    available = cores - client
    demand = idle + n * session + n * fps * frame_ms / 1e3
    fits = (available - idle) / (session + fps * frame_ms / 1e3)
    best = max(rows, key=lambda r: r["processed_fps"])
    if model["fit"]:
        text = (f"**CPU.** Over the rows the server's CPU fits cores = {idle:.2f} + "
                f"{session:.2f} x sessions + {frame_ms:.0f} ms x processed frames/s: each "
                f"processed frame costs **{frame_ms:.0f} ms of CPU**, each live session "
                f"{session:.2f} cores whatever its frame rate (drone simulation, flight map), the "
                f"idle server {idle:.2f}. ")
    else:
        text = f"**CPU.** The server spends **{frame_ms:.0f} ms of CPU per processed frame**. "
    text += (
        f"A frame's CPU covers decoding ({decode:.0f} ms median) and tracking ({track:.0f} ms "
        f"median, on the clock, {calm['sessions']} x {calm['fps']:g} fps), TSDF fusion of one "
        f"frame in {Settings().fuse_every} and of keyframes, and the map preview. {n} sessions at "
        f"{fps:g} fps need **{demand:.2f} cores**; this machine has {cores}, of which the load "
        f"tester took {client:.2f}, leaving {available:.2f} for the server: enough for about "
        f"**{fits:.1f} sessions at {fps:g} fps**. The most measured was "
        f"{best['processed_fps']:.1f} processed frames/s in total ({best['sessions']} x "
        f"{best['fps']:g} fps). One session's frames are tracked one at a time, so a session "
        f"cannot exceed ~{1e3 / max(track, 1e-3):.0f} fps whatever the cores. ")
    busiest = max(r["server"]["cpu_s"] / r["server"]["wall_s"] for r in rows)
    if busiest < 0.8 * available and best["drop_rate"] > TARGET["drop_rate"]:
        text += (f"**Contention.** The server never used more than {busiest:.2f} cores although "
                 f"it dropped frames, and stage times grew with the sessions: other processes "
                 f"held the rest of the CPU (load average {load_before:.1f} before the run on "
                 f"{cores} cores), so these figures understate the server. ")
    memory = _memory_per_session(rows)
    if memory is not None:
        text += (f"**Memory** grows by about {memory[0]:.0f} MB per session ({memory[1]:.0f} MB "
                 f"with none): {memory[1] + 8 * memory[0]:.0f} MB for 8 sessions. ")
    target = next((r for r in rows if "target" in r), None)
    if demand > available:
        frame_budget = 1e3 * (available - idle - n * session) / (n * fps)
        text += f"**To hold {n} x {fps:g} fps** on {cores} cores "
        text += (f"the CPU per frame must fall to {frame_budget:.0f} ms "
                 f"({frame_ms / frame_budget:.1f}x less)" if frame_budget > 0
                 else "the per-session cost alone must fall first")
        text += f", or the server needs {demand + client:.1f} cores with the load tester beside it."
    elif target is not None and not target["target"]:
        text += (f"The CPU would suffice ({demand:.2f} of {available:.2f} cores), yet the target "
                 f"row fails: latency or drops come from elsewhere (contention, one frame at a "
                 f"time per session, the two-frames-in-flight window).")
    else:
        text += f"The CPU suffices: {demand:.2f} of {available:.2f} cores."
    return text


def _fmt(value, pattern: str = "{:.0f}") -> str:
    return "-" if value is None else pattern.format(value)


def markdown(rows: list[dict], meta: dict, analysis: str) -> str:
    quick = meta["quick"]
    lines = [f"# Server capacity{' — SMOKE RUN, not a measurement' if quick else ''}", ""]
    if quick:
        lines += [f"> **Smoke run** (`--quick`: {rows[0]['duration_s']:g} s per row on "
                  f"{meta['frames']} frames) on a shared, loaded machine: the figures only show "
                  f"that the pipeline works. Run `python benchmarks/capacity.py` on a quiet "
                  f"machine for the capacity table.", ""]
    lines += [
        f"{meta['date']}; machine: {meta['machine']}, {meta['cores']} cores, load average "
        f"{meta['load_before']:.2f} before / {meta['load_after']:.2f} after; sequence "
        f"{meta['dataset']} {meta['size'][0]}x{meta['size'][1]} ({meta['frames']} frames, played "
        f"back and forth, {meta['mean_frame_kb']:.0f} kB per frame); map fusion on (one frame "
        f"in {meta['fuse_every']} + keyframes); drone simulation: {meta['drone']}; "
        f"commit {meta['commit']}.", "",
        f"Command: `{meta['command']}`", "",
        f"Target: {TARGET['sessions']} sessions at {TARGET['fps']:g} fps with p95 <= "
        f"{TARGET['p95_ms']:.0f} ms and < {100 * TARGET['drop_rate']:.0f} % of captured frames "
        f"without a pose.", "",
        "| sessions | fps | p50 ms | p95 ms | p99 ms | processed fps / session | drop client | "
        "drop server | no pose | server CPU % | server RSS MB | load tester CPU % | failures | "
        "target |",
        "|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|---|",
    ]
    for r in rows:
        target = "-"
        if "target" in r:
            target = (f"p95 {_fmt(r['p95_ms'])} <= {TARGET['p95_ms']:.0f}, no pose "
                      f"{100 * r['drop_rate']:.1f} % < {100 * TARGET['drop_rate']:.0f} %: "
                      f"**{'PASS' if r['target'] else 'FAIL'}**")
        lines.append(
            f"| {r['sessions']} | {r['fps']:g} | {_fmt(r['p50_ms'])} | {_fmt(r['p95_ms'])} | "
            f"{_fmt(r['p99_ms'])} | {r['processed_fps_per_session']:.1f} | "
            f"{100 * r['client_drop_rate']:.1f} % | {100 * r['server_drop_rate']:.1f} % | "
            f"{100 * r['drop_rate']:.1f} % | {r['server']['cpu_percent']:.0f} | "
            f"{r['server']['rss_max_mb']:.0f} | {r['client_cpu_percent']:.0f} | {r['failures']} | "
            f"{target} |")
    lines += ["", "## What limits it", "", analysis, "", "## How to read it", "",
              "- **p50/p95/p99 ms**: send to pose, per frame, over every session of the row "
              "(loopback: no network in it).",
              "- **processed fps / session**: poses per second each phone gets back.",
              "- **drop client**: captured frames not sent because two frames already awaited "
              "answers (as a phone does); **drop server**: sent frames the server skipped for a "
              "newer one; **no pose**: every captured frame without a pose, the target's measure.",
              "- **server CPU %**: of one core (200 % = both cores of this machine); **RSS**: "
              "the server's peak resident memory during the row (a fresh server per row).",
              "- **load tester CPU %**: the clients run on the same machine and take that much "
              "from the server.", ""]
    return "\n".join(lines)


def console_table(rows: list[dict]) -> Table:
    table = Table(title="server capacity (latency ms; CPU % of one core)", box=box.SIMPLE_HEAD,
                  pad_edge=False, collapse_padding=True)
    for col in ("sess", "fps", "p50", "p95", "p99", "fps/sess", "no pose", "srv CPU", "RSS MB",
                "cli CPU", "fail", "target"):
        table.add_column(col, justify="right")
    for r in rows:
        table.add_row(str(r["sessions"]), f"{r['fps']:g}", _fmt(r["p50_ms"]), _fmt(r["p95_ms"]),
                      _fmt(r["p99_ms"]), f"{r['processed_fps_per_session']:.1f}",
                      f"{100 * r['drop_rate']:.1f}%", f"{r['server']['cpu_percent']:.0f}",
                      f"{r['server']['rss_max_mb']:.0f}", f"{r['client_cpu_percent']:.0f}",
                      str(r["failures"]), {True: "PASS", False: "FAIL"}.get(r.get("target"), "-"))
    return table


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("sequence", nargs="?",
                        default=str(REPO.parent / "shared" / "data" / "synthetic_room0"))
    parser.add_argument("--duration", type=float, default=30.0, help="seconds per row")
    parser.add_argument("--sessions", type=int, nargs="+", default=[1, 2, 4, 8])
    parser.add_argument("--fps", type=float, nargs="+", default=[15.0, 30.0])
    parser.add_argument("--frames", type=int, default=None, help="first N frames of the sequence")
    parser.add_argument("--quick", action="store_true",
                        help="smoke run: 5 s per row on 30 frames, labelled as such")
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results")
    args = parser.parse_args()
    if args.quick:
        args.duration, args.frames = min(args.duration, 5.0), args.frames or 30

    dataset = open_dataset(args.sequence)
    with console.status(f"encoding {dataset.name} ..."):
        seq = EncodedSequence.from_dataset(dataset, args.frames)
    load_before = os.getloadavg()[0]
    rows = []
    for fps in args.fps:
        for sessions in args.sessions:
            # A fresh server per row: rows share no memory, caches or leftover sessions.
            with tempfile.TemporaryDirectory() as tmp:
                log = Path(tmp) / "server.log"  # beside the data, gone with the folder
                server = ServerProcess(Path(tmp) / "data", server_environment(sessions + 1), log)
                try:
                    rows.append(run_row(server.url, seq, server.pid, sessions, fps,
                                        args.duration))
                finally:
                    server.terminate()
                if rows and rows[-1]["failures"]:
                    console.print(f"server log (tail):\n{log.read_text()[-3000:]}")
            console.print(console_table(rows[-1:]))

    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, text=True,
                            capture_output=True).stdout.strip()
    drone_states = sum(r["drone_states"] for r in rows)
    meta = {
        "date": f"{datetime.datetime.now():%Y-%m-%d %H:%M}", "quick": args.quick,
        "machine": platform.platform(), "cores": os.cpu_count(), "load_before": load_before,
        "load_after": os.getloadavg()[0], "dataset": dataset.name, "size": list(seq.size),
        "frames": len(seq.frames), "mean_frame_kb": seq.mean_bytes / 1e3,
        "fuse_every": Settings().fuse_every, "commit": commit or "?",
        "drone": f"on ({drone_states} drone_state messages)" if drone_states
        else "not running (no drone_state received; commands answered 'not ready')",
        "command": "python " + " ".join(sys.argv),
    }
    analysis = what_limits_it(rows, os.cpu_count() or 1, load_before)
    console.print(console_table(rows))
    console.print(analysis)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "capacity.md").write_text(markdown(rows, meta, analysis))
    report = {"meta": meta, "target": TARGET, "cpu_model": cpu_model(rows), "rows": rows,
              "analysis": analysis}
    (args.out / "capacity.json").write_text(json.dumps(report, indent=1))
    console.print(f"wrote {args.out / 'capacity.md'} and capacity.json")
    if any(r["failures"] for r in rows):
        for r in rows:
            for message in r["failure_messages"]:
                console.print(f"[red]{r['sessions']} x {r['fps']:g} fps: {message}[/red]")
        sys.exit(2)


if __name__ == "__main__":
    main()
