"""The capacity report's analysis (``benchmarks/capacity.py``): pure functions from made-up rows'
measured numbers to the report's figures and verdicts, and the server process tree's CPU read
from /proc for a tree whose members start and end between two snapshots."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from tests.support.paths import REPO

_spec = importlib.util.spec_from_file_location("capacity", REPO / "benchmarks" / "capacity.py")
capacity = sys.modules["capacity"] = importlib.util.module_from_spec(_spec)  # for dataclasses
_spec.loader.exec_module(capacity)

TARGET = capacity.TARGET  # 4 x 15 fps, p95 <= 100 ms, < 5 % without a pose


def row(
    sessions: int,
    fps: float,
    p95: float | None,
    drop: float,
    *,
    failures: int = 0,
    processed: int = 100,
    cpu_s: float = 3.0,
    wall_s: float = 10.0,
    busy: float = 0.5,
    client_pct: float = 10.0,
    idle_cores: float = 0.01,
    stages: dict | None = None,
) -> dict:
    """A row as run_row makes it, from the measured numbers the analysis reads."""
    server = {
        "machine_busy": busy,
        "mem_max_mb": 500.0 + 200 * sessions,
        "processes_max": 1,
        "consistent": True,
        **capacity.server_cpu_figures(cpu_s, wall_s, processed, idle_cores),
    }
    stages = stages or {"decode": 4.0, "track": 25.0, "track_cpu": 20.0, "track_sparse": 9.0}
    r = {
        "sessions": sessions,
        "fps": fps,
        "p50_ms": p95 and p95 / 2,
        "p95_ms": p95,
        "p99_ms": p95,
        "drop_rate": drop,
        "processed": processed,
        "failures": failures,
        "client_cpu_percent": client_pct,
        "server": server,
        "stages_ms": {k: {"median": v, "p95": 2 * v, "mean": v} for k, v in stages.items()},
    }
    r["meets"] = capacity.meets(r)
    return r


# ---- CPU per frame ----------------------------------------------------------------------------


def test_cpu_per_frame_is_the_rows_tree_cpu_over_the_frames_processed_by_all_sessions():
    f = capacity.server_cpu_figures(cpu_s=3.0, wall_s=10.0, processed=100, idle_cores=0.1)
    assert f["cores"] == pytest.approx(0.3)
    assert f["cpu_ms_per_frame"] == pytest.approx(30.0)  # 3000 ms / 100 frames
    # The idle server would have used 0.1 core x 10 s = 1 s of it.
    assert f["cpu_ms_per_frame_above_idle"] == pytest.approx(20.0)


def test_cpu_per_frame_is_undefined_without_frames_or_without_a_server():
    f = capacity.server_cpu_figures(cpu_s=2.0, wall_s=10.0, processed=0, idle_cores=0.0)
    assert f["cores"] == pytest.approx(0.2) and f["cpu_ms_per_frame"] is None
    assert f["cpu_ms_per_frame_above_idle"] is None
    assert capacity.server_cpu_figures(None, 10.0, 50, 0.0)["cores"] is None
    # Idle above the row's own CPU (noise) is not a negative cost.
    assert capacity.server_cpu_figures(0.5, 10.0, 10, 0.1)["cpu_ms_per_frame_above_idle"] == 0


# ---- the target and the verdict ---------------------------------------------------------------


def test_a_row_meets_the_target_at_its_limits_and_not_beyond():
    assert capacity.meets(row(4, 15, 100.0, 0.049))  # p95 <= 100 ms is inside
    assert not capacity.meets(row(4, 15, 100.1, 0.0))
    assert not capacity.meets(row(4, 15, 50.0, 0.05))  # < 5 % without a pose: 5 % is out
    assert not capacity.meets(row(4, 15, 50.0, 0.0, failures=1))
    assert not capacity.meets(row(4, 15, None, 1.0, processed=0))


def test_the_verdict_is_the_largest_sessions_x_fps_that_meets_the_target():
    rows = [
        row(1, 15, 40, 0.0),
        row(2, 15, 60, 0.01),
        row(4, 15, 180, 0.3),
        row(8, 15, 900, 0.8),
        row(1, 30, 50, 0.02),
        row(2, 30, 90, 0.04),
        row(4, 30, 400, 0.6),
        row(8, 30, 1200, 0.9),
    ]
    v = capacity.verdict(rows)
    # 2 x 30 offers 60 frames/s, as 4 x 15, which misses.
    assert v["largest"] == {
        "sessions": 2,
        "fps": 30,
        "offered_fps": 60,
        "p95_ms": 90,
        "drop_rate": 0.04,
    }
    assert v["meeting"] == [[1, 15], [2, 15], [1, 30], [2, 30]]
    assert v["target"] is False


def test_the_verdict_prefers_more_sessions_at_the_same_offered_rate():
    v = capacity.verdict([row(2, 30, 90, 0.0), row(4, 15, 80, 0.0), row(1, 15, 30, 0.0)])
    assert (v["largest"]["sessions"], v["largest"]["fps"]) == (4, 15)
    assert v["target"] is True


def test_the_verdict_says_none_when_no_row_meets_it_and_nothing_for_a_target_not_run():
    v = capacity.verdict([row(1, 15, 300, 0.2), row(2, 15, 600, 0.5)])
    assert v == {"largest": None, "meeting": [], "target": None}


def test_a_row_with_a_good_p95_but_a_failure_does_not_count():
    v = capacity.verdict([row(1, 15, 40, 0.0), row(8, 30, 40, 0.0, failures=2)])
    assert v["largest"]["sessions"] == 1


# ---- what limits it ---------------------------------------------------------------------------


IDLE = {"cores": 0.004, "wall_s": 5.0}


def test_what_limits_it_states_measured_figures_not_a_fit():
    rows = [
        row(1, 15, 40, 0.0, cpu_s=3.0, processed=150, busy=0.20),  # 20 ms / frame
        row(2, 15, 60, 0.01, cpu_s=7.0, processed=280, busy=0.40),  # 25 ms / frame
        row(
            4,
            15,
            400,
            0.4,
            cpu_s=18.0,
            processed=360,
            busy=0.97,
            client_pct=12.0,
            stages={"decode": 9.0, "track": 80.0, "track_cpu": 30.0},
        ),
    ]  # 50 ms / frame
    text = capacity.what_limits_it(rows, IDLE, cores=2)
    assert "**2 sessions x 15 fps**" in text and "p95 60 ms" in text
    assert "4 x 15 fps, **FAIL**: p95 400 ms (limit 100), 40.0 % without a pose" in text
    assert "0.4 % of one core" in text  # the idle server, measured
    assert "20 ms of CPU at 1 x 15 fps to 50 ms at 4 x 15 fps" in text
    # Target row: 18 s of CPU, of which 0.004 x 10 s idle: 17.96 s / 360 frames.
    assert "50 ms at the target row (50 ms above idle), where it used 1.80 cores" in text
    # The lightest row that misses had 97 % of 2 cores busy: 1.94 = 1.80 + 0.12 + 0.02.
    assert "**CPU-bound**" in text and "server 1.80, load tester 0.12, other processes 0.02" in text
    assert "track 25.0 -> 80.0" in text and "track_cpu 20.0 -> 30.0" in text
    assert "track_sparse" not in text  # sub-stages stay in the JSON
    assert "fit" not in text.lower()
    assert "Contention" not in text  # others held 0.02 cores at most


def test_what_limits_it_says_not_cpu_bound_and_names_other_processes():
    rows = [row(1, 15, 150, 0.2, cpu_s=4.0, busy=0.80, client_pct=10.0)]
    text = capacity.what_limits_it(rows, IDLE, cores=2)
    assert "**Verdict.** No row run meets" in text and "**not CPU-bound**" in text
    # 0.8 x 2 cores busy - 0.4 server - 0.1 load tester = 1.1 cores for others.
    assert "up to 1.10 at 1 x 15 fps" in text
    assert "target" not in text.split("**CPU.**")[0].replace("meets p95", "")  # not run


def test_what_limits_it_without_a_processed_frame():
    rows = [row(1, 15, None, 1.0, processed=0, failures=1)]
    assert "No frame was processed" in capacity.what_limits_it(rows, IDLE, cores=2)


# ---- the server's process tree ----------------------------------------------------------------


def stat(pid: int, ppid: int, self_s: float, children_s: float = 0.0, start: int = 1):
    return capacity.ProcStat(pid, ppid, start, self_s, children_s)


def test_the_tree_holds_the_root_and_every_descendant_only():
    stats = {
        s.pid: s
        for s in [
            stat(1, 0, 9),
            stat(10, 1, 1),
            stat(11, 10, 2),
            stat(12, 11, 3),
            stat(13, 11, 4),
            stat(20, 1, 5),
            stat(21, 20, 6),
        ]
    }
    assert set(capacity.descendants(stats, 10)) == {10, 11, 12, 13}
    assert capacity.descendants(stats, 99) == {}
    tree = capacity.descendants(stats, 11)
    assert capacity.tree_cpu_s(tree) == pytest.approx(9.0)


def test_cpu_of_a_reaped_child_moves_into_its_parent_and_is_counted_once():
    before = {1: stat(1, 0, 1.0), 2: stat(2, 1, 0.5)}
    # Child 2 used 0.3 s more, exited and was reaped by 1: its 0.8 s are now 1's children time.
    after = {1: stat(1, 0, 1.2, children_s=0.8)}
    assert capacity.tree_cpu_s(after) - capacity.tree_cpu_s(before) == pytest.approx(0.5)
    assert not capacity.same_tree(before, after)
    assert capacity.same_tree(before, dict(before))
    # Same pids but a reap in between, or a pid reused by a new process: not consistent.
    assert not capacity.same_tree(before, {1: stat(1, 0, 1.0, 0.1), 2: stat(2, 1, 0.5)})
    assert not capacity.same_tree(before, {1: stat(1, 0, 1.0), 2: stat(2, 1, 0.5, start=7)})


TREE_SCRIPT = textwrap.dedent("""
    import os, sys, time

    def burn(s):
        t = time.process_time()
        while time.process_time() - t < s:
            pass

    sys.stdout.write("ready\\n"); sys.stdout.flush()
    sys.stdin.readline()
    burn(0.1)                                   # the root itself
    child = os.fork()
    if child == 0:                              # a child that ends during the interval
        burn(0.2); os._exit(0)
    os.waitpid(child, 0)
    r, w = os.pipe()
    middle = os.fork()
    if middle == 0:                             # a forkserver-like child that stays alive...
        grandchild = os.fork()
        if grandchild == 0:                     # ...and reaps a worker that ended
            burn(0.2); os._exit(0)
        os.waitpid(grandchild, 0)
        burn(0.1)
        os.write(w, b"x")
        sys.stdin.readline()
        os._exit(0)
    os.read(r, 1)
    sys.stdout.write("done\\n"); sys.stdout.flush()
    sys.stdin.readline()
    os.waitpid(middle, 0)
""")


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs Linux /proc")
def test_the_tree_cpu_counts_children_and_grandchildren_that_started_and_ended_in_between():
    proc = subprocess.Popen(
        [sys.executable, "-c", TREE_SCRIPT],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout.readline() == "ready\n"
        before, ok_before = capacity.snapshot_tree(proc.pid)
        assert ok_before and set(before) == {proc.pid}
        proc.stdin.write("go\n")
        proc.stdin.flush()
        assert proc.stdout.readline() == "done\n"
        after, ok_after = capacity.snapshot_tree(proc.pid)
        assert ok_after and len(after) == 2  # the root and the living middle child
        used = capacity.tree_cpu_s(after) - capacity.tree_cpu_s(before)
        # 0.1 root + 0.2 ended child + 0.2 ended grandchild + 0.1 middle = 0.6 s, plus forks;
        # the root's own CPU alone would be about 0.1 s.
        assert 0.55 <= used <= 0.8, used
        assert after[proc.pid].self_s - before[proc.pid].self_s < 0.3
    finally:
        proc.stdin.close()
        proc.wait(10)


def test_the_markdown_shows_figures_beside_the_target_and_the_stage_medians():
    rows = [row(1, 15, 40, 0.0, busy=0.2), row(4, 15, 400, 0.4, busy=0.97)]
    for r in rows:
        r.update(
            processed_fps_per_session=14.0,
            client_drop_rate=r["drop_rate"],
            server_drop_rate=0.0,
            duration_s=5.0,
        )
    rows[1]["target"] = rows[1]["meets"]
    meta = {
        "quick": False,
        "date": "2026-01-01 00:00",
        "commit": "abc1234",
        "machine": "m",
        "cores": 2,
        "load_before": 0.1,
        "load_after": 1.0,
        "dataset": "d",
        "size": [640, 480],
        "frames": 30,
        "mean_frame_kb": 200.0,
        "fuse_every": 3,
        "drone": "on",
        "command": "python benchmarks/capacity.py",
        "verdict": capacity.verdict(rows),
    }
    md = capacity.markdown(rows, meta, IDLE, capacity.what_limits_it(rows, IDLE, cores=2))
    assert "commit abc1234" in md and "0.4 % of one core" in md
    assert "that meets those limits: **1 session x 15 fps**" in md
    assert "p95 400 <= 100, no pose 40.0 % < 5 %: **FAIL**" in md
    assert "| 1 | 15 | 4.0 | 25.0 | 20.0 |" in md  # decode, track, track_cpu medians
    assert "## What limits it" in md and "| 0.30 | 30 (29) |" in md
    # Where the sessions start: a report from before the option played them in lockstep.
    assert "every session at the same frame at once (lockstep)" in md
    md = capacity.markdown(rows, {**meta, "lockstep": False}, IDLE, "")
    assert "each session starting elsewhere in it" in md and "lockstep" not in md
