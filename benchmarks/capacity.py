"""Capacity: how many phones one server holds, with map fusion and the drone simulation on.

Starts ``python -m server serve`` in its own process (a fresh one per row), measures the idle
server for a few seconds with no session, then runs the load tester (``server/client/loadtest.py``)
in this process for every combination of sessions (1, 2, 4, 8) and frame rate (15, 30 fps), one
after another. Writes ``benchmarks/results/capacity.md`` and ``capacity.json``: per row the
latency percentiles, processed fps per session, drop rates (client side, server side, and every
captured frame without a pose), the server's CPU (cores, and ms of CPU per processed frame), the
machine's busy share, the load tester's own CPU, the server's peak memory and the medians of the
server's stage timings; the verdict (the largest sessions x fps among the rows that meets p95 <=
100 ms and < 5 % of captured frames without a pose; the target row, 4 x 15 fps, PASS/FAIL); and
what limits it, stated from those measured figures only (no model is fitted).

    python benchmarks/capacity.py [SEQUENCE] [--duration 30] [--sessions 1 2 4 8] [--fps 15 30]
    python benchmarks/capacity.py --quick     # smoke run: 5 s per row on 30 frames

Each session starts elsewhere in the sequence (the load tester's default: phones in a room are
each at another point of their walk); ``--lockstep`` plays the same frame on every session at
once, the worst case, where each hard stretch of the sequence reaches every session together.

**Server CPU is the whole process tree's.** Sessions may run in worker processes (children of
the server, or grandchildren through a multiprocessing forkserver), so the server's CPU is summed
over every process descending from the ``python -m server serve`` pid (``ppid`` links in
``/proc/*/stat``). Per process, ``utime + stime`` is its own CPU (all its threads, exited ones
included) and ``cutime + cstime`` that of its children that exited and were reaped by it (the
kernel adds a reaped child's own and children's times to its parent's). So the sum of
``utime + stime + cutime + cstime`` over the live tree is all the CPU the tree has ever used,
dead members included, and the CPU of a row is that sum at the row's end minus at its start:
processes that started and ended during the row count through their parent's ``cutime``,
processes alive at the start and gone at the end count their share before the start in the
start sum, their whole life in the end sum (in their parent). Reading ``/proc`` is not atomic: a
child read and then reaped before its parent is read would count twice, a parent read before its
child is reaped and the child then missed, not at all. A snapshot is therefore read twice and
kept only when both reads hold the same processes (pid and start time) with the same
``cutime + cstime`` (nothing reaped in between); else it is read again (the row records whether
that succeeded). Not counted: a process that leaves the tree before being reaped (an orphan,
re-parented to init when its parent dies first), and a child reaped by nobody (SIGCHLD ignored).
Each row (and the idle measure) starts once the fresh server's start-up work has ended (its
tree below 0.1 core; /healthz answers earlier, e.g. while a forkserver still preloads the session
modules), so that work is in no figure. A row's CPU does include the idle server (event loop,
background threads) and every session's fixed costs (drone simulation, flight map); the idle
figure, measured before the first row, is reported beside it, and "ms per frame above idle"
takes it off.

The load tester shares the machine with the server (loopback): its CPU is reported, and the
machine's busy share (``/proc/stat``) tells whether a row had cores to spare.
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
from collections import Counter, defaultdict
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # run from anywhere, installed or not

from rich import box  # noqa: E402
from rich.console import Console  # noqa: E402
from rich.table import Table  # noqa: E402

from server.client.loadtest import (  # noqa: E402
    FRAME_PROFILES,
    EncodedSequence,
    LoadTestConfig,
    live_line,
    run_loadtest,
)
from server.client.server_process import ServerProcess  # noqa: E402
from server.config import Config  # noqa: E402
from server.datasets import open_dataset  # noqa: E402

TARGET = {"sessions": 4, "fps": 15.0, "p95_ms": 100.0, "drop_rate": 0.05}
# A row counts as CPU-saturated when the machine's cores were at least this busy (all
# processes): the server could not have had more CPU, whatever it needed.
SATURATED = 0.9
# Other processes (neither the server nor the load tester) holding at least this many cores
# during a row are named in the analysis: they took CPU from the server.
OTHERS_NOTED_CORES = 0.25
TICK_S = 1.0 / os.sysconf("SC_CLK_TCK")
console = Console(width=None if sys.stdout.isatty() else 160)  # logs: the table unwrapped


# ---- the server's process tree, from /proc ------------------------------------------------------


@dataclass(frozen=True)
class ProcStat:
    """One process's line of ``/proc/<pid>/stat``. start: start time, clock ticks after boot
    (with pid, identifies the process); self_s: utime + stime, CPU seconds of all its threads;
    children_s: cutime + cstime, CPU seconds of its exited children that it reaped."""

    pid: int
    ppid: int
    start: int
    self_s: float
    children_s: float


def read_stat(pid: int) -> ProcStat | None:
    """``/proc/<pid>/stat`` parsed, or None once the process is gone."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    f = text.rsplit(")", 1)[1].split()  # the command name may hold spaces and ')'
    return ProcStat(
        pid,
        int(f[1]),
        int(f[19]),
        (int(f[11]) + int(f[12])) * TICK_S,
        (int(f[13]) + int(f[14])) * TICK_S,
    )


def descendants(stats: dict[int, ProcStat], root: int) -> dict[int, ProcStat]:
    """root and every process below it (ppid links); empty when root is not in stats."""
    children: dict[int, list[int]] = defaultdict(list)
    for s in stats.values():
        children[s.ppid].append(s.pid)
    tree, todo = {}, [root] if root in stats else []
    while todo:
        pid = todo.pop()
        tree[pid] = stats[pid]
        todo += children[pid]
    return tree


def scan_tree(root: int) -> dict[int, ProcStat]:
    """The process tree under root as it is now (one pass over /proc)."""
    stats = {}
    for name in os.listdir("/proc"):
        if name.isdigit() and (s := read_stat(int(name))) is not None:
            stats[s.pid] = s
    return descendants(stats, root)


def same_tree(a: dict[int, ProcStat], b: dict[int, ProcStat]) -> bool:
    """Whether two reads hold the same processes, none of which reaped a child in between (its
    children_s unchanged): then each process of the first read was read while it still
    existed and before any CPU moved from a child to its parent, so its sum is exact."""
    return a.keys() == b.keys() and all(
        a[p].start == b[p].start and a[p].children_s == b[p].children_s for p in a
    )


def tree_cpu_s(tree: dict[int, ProcStat]) -> float:
    """CPU seconds the tree has used since its root started: its live processes' own CPU plus
    the CPU of every exited descendant that was reaped inside the tree (in some cutime/cstime)."""
    return sum(s.self_s + s.children_s for s in tree.values())


def snapshot_tree(root: int, attempts: int = 20) -> tuple[dict[int, ProcStat], bool]:
    """(a consistent read of the tree, True); (the last read, False) when processes kept
    starting or ending through every attempt."""
    first = scan_tree(root)
    for _ in range(attempts):
        second = scan_tree(root)
        if same_tree(first, second):
            return first, True
        first = second
        time.sleep(0.02)
    return first, False


def memory_mb(pid: int) -> float:
    """A process's proportional set size (PSS), MB: pages shared by several processes of the
    tree (a forked worker and its parent) count once over them, unlike RSS. Falls back to RSS
    without smaps_rollup (Linux < 4.14); 0 once the process is gone."""
    for path, key in ((f"/proc/{pid}/smaps_rollup", "Pss:"), (f"/proc/{pid}/status", "VmRSS:")):
        try:
            for line in Path(path).read_text().splitlines():
                if line.startswith(key):
                    return int(line.split()[1]) / 1024
        except OSError:
            continue
    return 0.0


def machine_cpu_s() -> tuple[float, float]:
    """(busy, total) CPU seconds of the whole machine since boot, all cores (``/proc/stat``);
    busy is everything but idle and iowait (steal counts as busy: the core was not ours)."""
    values = [int(v) for v in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    idle = values[3] + (values[4] if len(values) > 4 else 0)
    total = sum(values[:8])  # guest time is already inside user and nice
    return (total - idle) * TICK_S, total * TICK_S


class TreeSampler:
    """The server process tree's CPU over a ``with`` block (consistent snapshots at its start
    and end, see the module docstring), its memory (summed PSS, sampled every ``every_s`` in a
    background thread) and the machine's busy share over the same interval."""

    def __init__(self, root: int, every_s: float = 0.5) -> None:
        self.root, self.every_s = root, every_s
        self._stop = threading.Event()
        self._memory: list[float] = []
        self._processes = 0

    def _sample_memory(self) -> None:
        tree = scan_tree(self.root)
        if tree:
            self._memory.append(sum(memory_mb(p) for p in tree))
            self._processes = max(self._processes, len(tree))

    def __enter__(self) -> TreeSampler:
        self._machine0 = machine_cpu_s()
        self._tree0, self._consistent0 = snapshot_tree(self.root)
        self._t0 = time.monotonic()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        return self

    def _run(self) -> None:
        self._sample_memory()
        while not self._stop.wait(self.every_s):
            self._sample_memory()

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()
        self.wall_s = time.monotonic() - self._t0
        tree1, consistent1 = snapshot_tree(self.root)
        machine1 = machine_cpu_s()
        self._sample_memory()
        self.cpu_s = tree_cpu_s(tree1) - tree_cpu_s(self._tree0) if tree1 else None
        self.consistent = self._consistent0 and consistent1
        busy, total = (b - a for a, b in zip(self._machine0, machine1, strict=True))
        self.machine_busy = busy / total if total > 0 else 0.0

    def summary(self) -> dict:
        """cpu_s: CPU seconds of the tree during the block; cores: cpu_s / wall_s (1.0 = one core
        busy); machine_busy: share of all the machine's cores busy (every process), 0-1;
        mem_max_mb / mem_end_mb: the tree's summed PSS, MB; processes_max: the most processes
        seen in the tree; consistent: both CPU snapshots were consistent reads."""
        return {
            "cpu_s": self.cpu_s,
            "wall_s": self.wall_s,
            "cores": self.cpu_s / self.wall_s if self.cpu_s is not None else None,
            "machine_busy": self.machine_busy,
            "mem_max_mb": max(self._memory, default=0.0),
            "mem_end_mb": self._memory[-1] if self._memory else 0.0,
            "processes_max": self._processes,
            "consistent": self.consistent,
        }


# ---- pure analysis: measured numbers in, figures and verdicts out -------------------------------


def server_cpu_figures(
    cpu_s: float | None, wall_s: float, processed: int, idle_cores: float
) -> dict:
    """A row's server CPU: cores (CPU s / wall s; 1.0 = one core busy); cpu_ms_per_frame: the
    tree's CPU ms during the row / frames processed by all its sessions; ..._above_idle: the
    same after taking off what the idle server would have used over the row's wall time. None
    where undefined (no frame processed, server gone)."""
    if cpu_s is None:
        return {"cores": None, "cpu_ms_per_frame": None, "cpu_ms_per_frame_above_idle": None}
    per_frame = above = None
    if processed:
        per_frame = 1e3 * cpu_s / processed
        above = 1e3 * max(0.0, cpu_s - idle_cores * wall_s) / processed
    return {
        "cores": cpu_s / wall_s,
        "cpu_ms_per_frame": per_frame,
        "cpu_ms_per_frame_above_idle": above,
    }


def _summed(counts) -> dict[str, int]:
    """Counts by name ({name: n} each) added up."""
    total: Counter = Counter()
    for c in counts:
        total.update(c)
    return dict(total)


def _share(row: dict, key: str, name: str) -> float | None:
    """Percentage of the row's poses whose ``key`` (states, recoveries) count ``name``."""
    if key not in row or not row["processed"]:
        return None
    return 100 * row[key].get(name, 0) / row["processed"]


def meets(row: dict, target: dict = TARGET) -> bool:
    """p95 <= target ms, the share of captured frames without a pose below the target, some
    frame processed, no failure."""
    return bool(
        row["p95_ms"] is not None
        and row["p95_ms"] <= target["p95_ms"]
        and row["drop_rate"] < target["drop_rate"]
        and row["processed"] > 0
        and not row["failures"]
    )


def _load(row: dict) -> tuple[float, int]:
    """Offered frames per second (sessions x fps), then sessions: more phones win a tie."""
    return row["sessions"] * row["fps"], row["sessions"]


def verdict(rows: list[dict], target: dict = TARGET) -> dict:
    """largest: the row with the largest sessions x fps (captured frames per second offered;
    ties go to more sessions) among those that meet the target's latency and drop limits, as
    {sessions, fps, offered_fps, p95_ms, drop_rate}, or None; meeting: [sessions, fps] of every
    row that meets them; target: True/False for the target row (4 x 15 fps), None if not run."""
    ok = [r for r in rows if meets(r, target)]
    best = max(ok, key=_load, default=None)
    target_row = next(
        (r for r in rows if r["sessions"] == target["sessions"] and r["fps"] == target["fps"]), None
    )
    return {
        "largest": None
        if best is None
        else {
            "sessions": best["sessions"],
            "fps": best["fps"],
            "offered_fps": _load(best)[0],
            "p95_ms": best["p95_ms"],
            "drop_rate": best["drop_rate"],
        },
        "meeting": [[r["sessions"], r["fps"]] for r in ok],
        "target": None if target_row is None else meets(target_row, target),
    }


def shown_stages(stages_ms: dict) -> list[str]:
    """The stages worth a column: the top-level ones and the tracking thread's own CPU time
    (track_cpu); the tracker's sub-stages stay in the JSON."""
    return [k for k in sorted(stages_ms) if not k.startswith("track_") or k == "track_cpu"]


def _sessions(n: int) -> str:
    return f"{n} session{'' if n == 1 else 's'}"


def _name(row: dict) -> str:
    return f"{row['sessions']} x {row['fps']:g} fps"


def _stage(row: dict, name: str) -> float | None:
    return row["stages_ms"].get(name, {}).get("median")


def what_limits_it(rows: list[dict], idle: dict, cores: int, target: dict = TARGET) -> str:
    """A paragraph stating the measured figures that decide capacity: the verdict, the idle
    server's CPU, CPU ms per processed frame, whether the first row that misses the target had
    cores to spare, the stage medians from the lightest to the heaviest row, other processes'
    CPU and memory. Every number is one measured in a row (or a difference of two): no fit.

    rows: the run's rows (sessions, fps, p95_ms, drop_rate, processed, failures, stages_ms,
    client_cpu_percent, server: {cores, cpu_ms_per_frame, cpu_ms_per_frame_above_idle,
    machine_busy, mem_max_mb}); idle: {cores, wall_s}; cores: the machine's."""
    if not any(r["processed"] for r in rows):
        return "No frame was processed: nothing to analyse (see the failures)."
    v, limit = (
        verdict(rows, target),
        (
            f"p95 <= {target['p95_ms']:.0f} ms and < "
            f"{100 * target['drop_rate']:.0f} % of captured frames "
            f"without a pose"
        ),
    )
    by_load = sorted(rows, key=_load)
    lightest, heaviest = by_load[0], by_load[-1]
    parts = []

    if v["largest"] is not None:
        b = v["largest"]
        parts.append(
            f"**Verdict.** The largest load run that meets {limit} is "
            f"**{_sessions(b['sessions'])} x {b['fps']:g} fps** "
            f"({b['offered_fps']:g} captured frames/s): p95 {b['p95_ms']:.0f} ms, "
            f"{100 * b['drop_rate']:.1f} % without a pose."
        )
    else:
        parts.append(
            f"**Verdict.** No row run meets {limit}; the lightest, {_name(lightest)}, "
            f"had p95 {_fmt(lightest['p95_ms'])} ms and "
            f"{100 * lightest['drop_rate']:.1f} % without a pose."
        )
    target_row = next(
        (r for r in rows if r["sessions"] == target["sessions"] and r["fps"] == target["fps"]), None
    )
    if target_row is not None:
        parts.append(
            f"The target, {_name(target_row)}, **{'PASS' if v['target'] else 'FAIL'}**: "
            f"p95 {_fmt(target_row['p95_ms'])} ms (limit {target['p95_ms']:.0f}), "
            f"{100 * target_row['drop_rate']:.1f} % without a pose (limit "
            f"{100 * target['drop_rate']:.0f} %)."
        )

    per_frame = [
        (r, r["server"]["cpu_ms_per_frame"])
        for r in rows
        if r["server"]["cpu_ms_per_frame"] is not None
    ]
    lo, hi = min(per_frame, key=lambda x: x[1]), max(per_frame, key=lambda x: x[1])
    text = (
        f"**CPU.** With no session the server used {100 * idle['cores']:.1f} % of one core "
        f"(measured over {idle['wall_s']:.0f} s). Per processed frame its process tree "
        f"spent {lo[1]:.0f} ms of CPU at {_name(lo[0])} to {hi[1]:.0f} ms at "
        f"{_name(hi[0])}"
    )
    if target_row is not None and target_row["server"]["cpu_ms_per_frame"] is not None:
        s = target_row["server"]
        text += (
            f"; {s['cpu_ms_per_frame']:.0f} ms at the target row "
            f"({s['cpu_ms_per_frame_above_idle']:.0f} ms above idle), where it used "
            f"{s['cores']:.2f} cores"
        )
    parts.append(
        text + ". A row's CPU per frame includes every session's fixed costs (drone "
        "simulation, flight map): where frames are dropped, each processed frame "
        "carries more of them."
    )

    missing = [r for r in by_load if not meets(r, target)]
    if missing:
        r = missing[0]
        busy = r["server"]["machine_busy"] * cores
        server, client = r["server"]["cores"] or 0.0, r["client_cpu_percent"] / 100
        split = (
            f"server {server:.2f}, load tester {client:.2f}, other processes "
            f"{max(0.0, busy - server - client):.2f}"
        )
        if r["server"]["machine_busy"] >= SATURATED:
            parts.append(
                f"**Limit.** At {_name(r)}, the lightest row that misses, the "
                f"machine's {cores} cores were {100 * r['server']['machine_busy']:.0f} % "
                f"busy ({split} cores): **CPU-bound**. The server got no more CPU than "
                f"that, so its figures there show what the cores allowed, not what it "
                f"needed."
            )
        else:
            busy_pct = 100 * r["server"]["machine_busy"]
            parts.append(
                f"**Limit.** At {_name(r)}, the lightest row that misses, the "
                f"machine's {cores} cores were only {busy_pct:.0f} % busy ({split} "
                f"cores): **not CPU-bound**. The misses come from waiting inside the "
                f"pipeline (one frame tracked at a time per session, at most two frames "
                f"in flight), not from a lack of cores: see the stage medians."
            )

    names = [k for k in shown_stages(lightest["stages_ms"]) if k in heaviest["stages_ms"]]
    if names:
        stages = ", ".join(
            f"{k} {_stage(lightest, k):.1f} -> {_stage(heaviest, k):.1f}" for k in names
        )
        text = f"**Stages** (median ms, {_name(lightest)} -> {_name(heaviest)}): {stages}."
        if "track" in names and "track_cpu" in names:
            text += " track minus track_cpu is time the tracking thread waited for a core."
        parts.append(text)

    crowded = [
        (
            r,
            r["server"]["machine_busy"] * cores
            - (r["server"]["cores"] or 0.0)
            - r["client_cpu_percent"] / 100,
        )
        for r in rows
    ]
    crowded = [(r, c) for r, c in crowded if c >= OTHERS_NOTED_CORES]
    if crowded:
        worst = max(crowded, key=lambda x: x[1])
        parts.append(
            f"**Contention.** Processes other than the server and the load tester held "
            f"{OTHERS_NOTED_CORES:g} cores or more in {len(crowded)} of {len(rows)} rows "
            f"(up to {worst[1]:.2f} at {_name(worst[0])}): those rows understate the "
            f"server; rerun on a quiet machine."
        )

    few, many = min(rows, key=lambda r: r["sessions"]), max(rows, key=lambda r: r["sessions"])
    if many["sessions"] > few["sessions"]:
        parts.append(
            f"**Memory** (the server tree's peak PSS): {few['server']['mem_max_mb']:.0f} "
            f"MB at {_sessions(few['sessions'])}, {many['server']['mem_max_mb']:.0f} MB "
            f"at {many['sessions']}."
        )
    return "\n\n".join(parts)


# ---- running ------------------------------------------------------------------------------------


def server_environment(max_sessions: int) -> dict[str, str]:
    """Settings for the run: room for every session, no create rate limit (one load-test IP
    creates every session)."""
    return {"DRONESIM_MAX_SESSIONS": str(max_sessions), "DRONESIM_CREATE_RATE_PER_MIN": "0"}


def wait_until_settled(
    pid: int, below_cores: float = 0.1, window_s: float = 0.5, timeout_s: float = 60.0
) -> float:
    """Seconds waited until the server tree used less than ``below_cores`` over ``window_s``
    (or ``timeout_s`` passed). /healthz answers before the start-up's work ends (a forkserver
    preloading the session modules, for one): without this wait that work would count in the
    idle figure and in the first seconds of every row."""
    t0 = time.monotonic()
    before, _ = snapshot_tree(pid)
    while time.monotonic() - t0 < timeout_s:
        time.sleep(window_s)
        after, _ = snapshot_tree(pid)
        if not after or tree_cpu_s(after) - tree_cpu_s(before) < below_cores * window_s:
            break
        before = after
    return time.monotonic() - t0


def measure_idle(pid: int, seconds: float) -> dict:
    """The server tree's CPU with no session, once its start-up has settled: cpu_s, wall_s,
    cores (1.0 = one core busy), processes_max, consistent (see TreeSampler.summary)."""
    with console.status(f"idle server, {seconds:g} s ..."), TreeSampler(pid) as sampler:
        time.sleep(seconds)
    s = sampler.summary()
    return {k: s[k] for k in ("cpu_s", "wall_s", "cores", "processes_max", "consistent")}


def run_row(
    url: str,
    seq: EncodedSequence,
    pid: int,
    sessions: int,
    fps: float,
    duration_s: float,
    idle: dict,
    commit: str,
    lockstep: bool = False,
) -> dict:
    cfg = LoadTestConfig(
        url=url,
        sessions=sessions,
        fps=fps,
        duration_s=duration_s,
        client_name="capacity",
        lockstep=lockstep,
    )
    with console.status(f"{sessions} x {fps:g} fps ...") as status:

        def show(results, elapsed: float) -> None:
            status.update(
                f"{sessions} x {fps:g} fps, {elapsed:4.1f}/{duration_s:g} s | "
                f"{live_line(results, elapsed)}"
            )

        with TreeSampler(pid) as sampler:
            report = asyncio.run(run_loadtest(seq, cfg, on_progress=show))
    t = report["total"]
    server = sampler.summary()
    server.update(
        server_cpu_figures(server["cpu_s"], server["wall_s"], t["processed"], idle["cores"])
    )
    row = {
        "sessions": sessions,
        "fps": fps,
        "duration_s": duration_s,
        "commit": commit,
        **{k: t["latency"][k] for k in ("p50_ms", "p95_ms", "p99_ms")},
        "processed_fps_per_session": t["processed_fps_per_session"],
        "processed_fps": t["processed_fps"],
        **{
            k: t[k]
            for k in (
                "captured",
                "sent",
                "processed",
                "client_dropped",
                "server_dropped",
                "client_drop_rate",
                "server_drop_rate",
                "drop_rate",
                "errors",
                "failures",
            )
        },
        "server": server,
        "client_cpu_percent": report["client_cpu_percent"],
        "stages_ms": report["stages_ms"],
        "drone_states": sum(s["commands"]["drone_states"] for s in report["sessions"]),
        # Poses by tracking state and by recovery (a loss found again, a new segment, a merge):
        # a server behind drops frames, and wider gaps between frames lose track more often.
        "states": _summed(s["states"] for s in report["sessions"]),
        "recoveries": _summed(s.get("recoveries", {}) for s in report["sessions"]),
        "failure_messages": [f for s in report["sessions"] for f in s["failures"]][:10],
    }
    row["meets"] = meets(row)
    if sessions == TARGET["sessions"] and fps == TARGET["fps"]:
        row["target"] = row["meets"]
    return row


# ---- report -------------------------------------------------------------------------------------


def _fmt(value, pattern: str = "{:.0f}") -> str:
    return "-" if value is None else pattern.format(value)


def _target_cell(r: dict) -> str:
    """Figure and limit side by side on the target row, yes/no on the others."""
    if "target" not in r:
        return "yes" if r["meets"] else "no"
    return (
        f"p95 {_fmt(r['p95_ms'])} <= {TARGET['p95_ms']:.0f}, no pose "
        f"{100 * r['drop_rate']:.1f} % < {100 * TARGET['drop_rate']:.0f} %: "
        f"**{'PASS' if r['target'] else 'FAIL'}**"
    )


def _size(meta: dict) -> str:
    """The depth's size in a report's meta (reports before profiles: the colour's)."""
    w, h = meta.get("depth_size") or meta["size"]
    return f"{w}x{h}"


def _starts(meta: dict) -> str:
    """Where the sessions start in the sequence (reports before ``--lockstep``: together)."""
    if meta.get("lockstep", True):
        return "every session at the same frame at once (lockstep)"
    return "each session starting elsewhere in it"


def markdown(rows: list[dict], meta: dict, idle: dict, analysis: str) -> str:
    quick = meta["quick"]
    lines = [f"# Server capacity{' — SMOKE RUN, not a measurement' if quick else ''}", ""]
    if quick:
        lines += [
            f"> **Smoke run** (`--quick`: {rows[0]['duration_s']:g} s per row on "
            f"{meta['frames']} frames) on a shared, loaded machine: the figures only show "
            f"that the pipeline works. Run `python benchmarks/capacity.py` on a quiet "
            f"machine for the capacity table.",
            "",
        ]
    v = meta["verdict"]
    largest = (
        "none"
        if v["largest"] is None
        else f"**{_sessions(v['largest']['sessions'])} x {v['largest']['fps']:g} fps**"
    )
    lines += [
        f"{meta['date']}; commit {meta['commit']}; machine: {meta['machine']}, {meta['cores']} "
        f"cores, load average {meta['load_before']:.2f} before / {meta['load_after']:.2f} after; "
        f"sequence {meta['dataset']} as {meta.get('profile', 'kinect')} sends it: colour "
        f"{meta['size'][0]}x{meta['size'][1]}, depth {_size(meta)} ({meta['frames']} "
        f"frames, played back and forth, {_starts(meta)}, {meta['mean_frame_kb']:.0f} kB per "
        f"frame); map fusion "
        f"on (one frame in {meta['fuse_every']} + keyframes); drone simulation: {meta['drone']}; "
        f"idle server (no session, {idle['wall_s']:.0f} s): {100 * idle['cores']:.1f} % of one "
        f"core.",
        "",
        f"Command: `{meta['command']}`",
        "",
        f"Target: {TARGET['sessions']} sessions at {TARGET['fps']:g} fps with p95 <= "
        f"{TARGET['p95_ms']:.0f} ms and < {100 * TARGET['drop_rate']:.0f} % of captured frames "
        f"without a pose. Largest sessions x fps run that meets those limits: {largest}.",
        "",
        "| sessions | fps | p50 ms | p95 ms | p99 ms | processed fps / session | drop client | "
        "drop server | no pose | server cores | server CPU ms / frame (above idle) | machine busy "
        "| load tester cores | server processes | server PSS MB | failures | meets target |",
        "|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|---|",
    ]
    for r in rows:
        s = r["server"]
        lines.append(
            f"| {r['sessions']} | {r['fps']:g} | {_fmt(r['p50_ms'])} | {_fmt(r['p95_ms'])} | "
            f"{_fmt(r['p99_ms'])} | {r['processed_fps_per_session']:.1f} | "
            f"{100 * r['client_drop_rate']:.1f} % | {100 * r['server_drop_rate']:.1f} % | "
            f"{100 * r['drop_rate']:.1f} % | {_fmt(s['cores'], '{:.2f}')} | "
            f"{_fmt(s['cpu_ms_per_frame'])} ({_fmt(s['cpu_ms_per_frame_above_idle'])}) | "
            f"{100 * s['machine_busy']:.0f} % | {r['client_cpu_percent'] / 100:.2f} | "
            f"{s['processes_max']}{'' if s['consistent'] else '*'} | {s['mem_max_mb']:.0f} | "
            f"{r['failures']} | {_target_cell(r)} |"
        )
    stages = sorted({k for r in rows for k in shown_stages(r["stages_ms"])})
    lines += [
        "",
        "Server stage timings, median ms per row (from the poses' `timings_ms`), and the share "
        "of poses lost and of poses in a new map segment (tracking recovery, PROTOCOL.md):",
        "",
        "| sessions | fps | " + " | ".join(stages) + " | lost | in a segment |",
        "|--:|--:|" + "--:|" * len(stages) + "--:|--:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['sessions']} | {r['fps']:g} | "
            + " | ".join(_fmt(_stage(r, k), "{:.1f}") for k in stages)
            + f" | {_fmt(_share(r, 'states', 'lost'), '{:.1f} %')}"
            + f" | {_fmt(_share(r, 'recoveries', 'segment'), '{:.1f} %')} |"
        )
    lines += [
        "",
        "## What limits it",
        "",
        analysis,
        "",
        "## How to read it",
        "",
        "- **p50/p95/p99 ms**: send to pose, per frame, over every session of the row "
        "(loopback: no network in it).",
        "- **processed fps / session**: poses per second each phone gets back.",
        "- **drop client**: captured frames not sent because two frames already awaited "
        "answers (as a phone does); **drop server**: sent frames the server skipped for a "
        "newer one; **no pose**: every captured frame without a pose, the target's measure.",
        "- **server cores**: CPU seconds of the server's whole process tree (the server "
        "and every process below it, those that ended during the row included) per "
        "second of the row (1.00 = one core busy); **CPU ms / frame**: those CPU "
        "seconds over the frames processed by all the row's sessions, and in brackets the "
        "same after taking off the idle server's CPU over the row.",
        "- **machine busy**: share of all cores busy with any process (`/proc/stat`); at "
        f">= {100 * SATURATED:.0f} % the row is CPU-bound. **load tester cores**: the "
        "clients run on the same machine and take that much from the server.",
        "- **server processes**: the most processes seen in the server's tree (1: "
        "sessions in the server process); `*`: a CPU snapshot of the tree kept changing "
        "and may be off by one process's CPU. **PSS**: the tree's peak proportional "
        "memory (pages shared between its processes counted once), a fresh server per "
        "row.",
        "- **meets target**: p95 and no-pose share within the target's limits and no "
        "failure; the verdict is the largest sessions x fps among those rows.",
        "",
    ]
    return "\n".join(lines)


def console_table(rows: list[dict]) -> Table:
    table = Table(
        title="server capacity (latency ms; cores: 1.00 = one core busy)",
        box=box.SIMPLE_HEAD,
        pad_edge=False,
        collapse_padding=True,
    )
    for col in (
        "sess",
        "fps",
        "p50",
        "p95",
        "p99",
        "fps/sess",
        "no pose",
        "srv cores",
        "CPU ms/frame",
        "busy",
        "cli cores",
        "procs",
        "PSS MB",
        "fail",
        "meets",
    ):
        table.add_column(col, justify="right")
    for r in rows:
        s = r["server"]
        meets_cell = (
            {True: "PASS", False: "FAIL"}[r["target"]]
            if "target" in r
            else ("yes" if r["meets"] else "no")
        )
        table.add_row(
            str(r["sessions"]),
            f"{r['fps']:g}",
            _fmt(r["p50_ms"]),
            _fmt(r["p95_ms"]),
            _fmt(r["p99_ms"]),
            f"{r['processed_fps_per_session']:.1f}",
            f"{100 * r['drop_rate']:.1f}%",
            _fmt(s["cores"], "{:.2f}"),
            f"{_fmt(s['cpu_ms_per_frame'])} ({_fmt(s['cpu_ms_per_frame_above_idle'])})",
            f"{100 * s['machine_busy']:.0f}%",
            f"{r['client_cpu_percent'] / 100:.2f}",
            f"{s['processes_max']}{'' if s['consistent'] else '*'}",
            f"{s['mem_max_mb']:.0f}",
            str(r["failures"]),
            meets_cell,
        )
    return table


def git_commit() -> str:
    """HEAD's short hash, with '+uncommitted' when tracked files differ from it."""

    def git(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run(["git", *args], cwd=REPO, text=True, capture_output=True)

    commit = git("rev-parse", "--short", "HEAD").stdout.strip()
    if not commit:
        return "?"
    return commit + ("+uncommitted" if git("diff", "--quiet", "HEAD").returncode else "")


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "sequence", nargs="?", default=str(REPO.parent / "shared" / "data" / "synthetic_room0")
    )
    parser.add_argument("--duration", type=float, default=30.0, help="seconds per row")
    parser.add_argument("--sessions", type=int, nargs="+", default=[1, 2, 4, 8])
    parser.add_argument("--fps", type=float, nargs="+", default=[15.0, 30.0])
    parser.add_argument("--frames", type=int, default=None, help="first N frames of the sequence")
    parser.add_argument(
        "--idle",
        type=float,
        default=5.0,
        help="seconds the idle server is measured before the first row",
    )
    parser.add_argument(
        "--quick",
        action="store_true",
        help="smoke run: 5 s per row on 30 frames, 2 s idle, labelled as such",
    )
    parser.add_argument(
        "--profile",
        choices=sorted(FRAME_PROFILES),
        default="kinect",
        help="the frames the phones send: kinect (as recorded, 640x480), arcore (live AR on a "
        "20:9 phone: colour 640x288, depth 160x72), iphone (a recording: 640x480, depth 256x192)",
    )
    parser.add_argument(
        "--lockstep",
        action="store_true",
        help="every session plays the same frame at once (the worst case), not each elsewhere "
        "in the sequence",
    )
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results")
    args = parser.parse_args()
    if args.quick:
        args.duration, args.frames = min(args.duration, 5.0), args.frames or 30
        args.idle = min(args.idle, 2.0)

    commit = git_commit()
    dataset = open_dataset(args.sequence)
    with console.status(f"encoding {dataset.name} ..."):
        seq = EncodedSequence.from_dataset(dataset, args.frames, profile=args.profile)
    load_before = os.getloadavg()[0]
    rows: list[dict] = []
    idle: dict | None = None
    for fps in args.fps:
        for sessions in args.sessions:
            # A fresh server per row: rows share no memory, caches or leftover sessions.
            with tempfile.TemporaryDirectory() as tmp:
                log = Path(tmp) / "server.log"  # beside the data, gone with the folder
                server = ServerProcess(Path(tmp) / "data", server_environment(sessions + 1), log)
                try:
                    with console.status("server start-up ..."):
                        settle_s = wait_until_settled(server.pid)
                    if idle is None:  # once, on the first row's server before its sessions
                        idle = measure_idle(server.pid, args.idle)
                        console.print(
                            f"idle server: {100 * idle['cores']:.1f} % of one core "
                            f"over {idle['wall_s']:.1f} s"
                        )
                    rows.append(
                        run_row(
                            server.url,
                            seq,
                            server.pid,
                            sessions,
                            fps,
                            args.duration,
                            idle,
                            commit,
                            args.lockstep,
                        )
                    )
                    rows[-1]["server"]["settle_s"] = settle_s
                finally:
                    server.terminate()
                if rows and rows[-1]["failures"]:
                    console.print(f"server log (tail):\n{log.read_text()[-3000:]}")
            console.print(console_table(rows[-1:]))

    assert idle is not None
    drone_states = sum(r["drone_states"] for r in rows)
    cores = os.cpu_count() or 1
    meta = {
        "date": f"{datetime.datetime.now():%Y-%m-%d %H:%M}",
        "quick": args.quick,
        "machine": platform.platform(),
        "cores": cores,
        "load_before": load_before,
        "load_after": os.getloadavg()[0],
        "dataset": seq.name,
        "size": list(seq.size),
        "depth_size": list(seq.depth_size or seq.size),
        "profile": seq.profile,
        "lockstep": args.lockstep,
        "frames": len(seq.frames),
        "mean_frame_kb": seq.mean_bytes / 1e3,
        "fuse_every": Config().mapping.fuse_every,
        "commit": commit,
        "drone": f"on ({drone_states} drone_state messages)"
        if drone_states
        else "not running (no drone_state received; commands answered 'not ready')",
        "command": "python " + " ".join(sys.argv),
        "verdict": verdict(rows),
    }
    analysis = what_limits_it(rows, idle, cores)
    console.print(console_table(rows))
    largest = meta["verdict"]["largest"]
    console.print(
        f"largest sessions x fps meeting p95 <= {TARGET['p95_ms']:.0f} ms and no pose "
        f"< {100 * TARGET['drop_rate']:.0f} %: "
        + ("none" if largest is None else f"{largest['sessions']} x {largest['fps']:g}")
    )
    console.print(analysis)
    args.out.mkdir(parents=True, exist_ok=True)
    # The Kinect-sized run is the report; a phone profile's goes beside it.
    stem = "capacity" if args.profile == "kinect" else f"capacity_{args.profile}"
    (args.out / f"{stem}.md").write_text(markdown(rows, meta, idle, analysis))
    report = {
        "meta": meta,
        "target": TARGET,
        "idle": idle,
        "verdict": meta["verdict"],
        "rows": rows,
        "analysis": analysis,
    }
    (args.out / f"{stem}.json").write_text(json.dumps(report, indent=1))
    console.print(f"wrote {args.out / (stem + '.md')} and {stem}.json")
    if any(r["failures"] for r in rows):
        for r in rows:
            for message in r["failure_messages"]:
                console.print(f"[red]{r['sessions']} x {r['fps']:g} fps: {message}[/red]")
        sys.exit(2)


if __name__ == "__main__":
    main()
