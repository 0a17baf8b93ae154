"""The command line, run as a user would: a separate process, real files."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np

from server.evaluation.trajectory import read_tum

REPO = Path(__file__).resolve().parents[1]


def run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "server", *args],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=300,
    )


def test_track_writes_trajectory_map_picture_and_metrics(shared_data, tmp_path):
    out = tmp_path / "out"
    proc = run_cli(
        "track", str(shared_data / "synthetic_room0"), "--frames", "8", "--out", str(out)
    )
    assert proc.returncode == 0, proc.stderr
    traj = read_tum(out / "trajectory.tum")
    assert len(traj) == 8  # one pose per input frame
    assert np.isfinite(traj.poses).all()
    ply = (out / "map.ply").read_bytes()
    assert ply.startswith(b"ply\nformat binary_little_endian")
    assert b"property uchar red" in ply
    png = (out / "trajectory.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000
    assert "ATE" in proc.stdout


def test_evaluate_prints_the_table_for_two_files(shared_data, tmp_path):
    gt = shared_data / "synthetic_room0" / "groundtruth.txt"
    proc = run_cli("evaluate", str(gt), str(gt))
    assert proc.returncode == 0, proc.stderr
    assert "ATE" in proc.stdout and "0.00" in proc.stdout


def test_a_missing_dataset_gives_one_clear_line_and_exit_status_1(tmp_path):
    proc = run_cli("track", str(tmp_path / "nowhere"), "--out", str(tmp_path / "o"))
    assert proc.returncode == 1
    assert "does not exist" in proc.stderr
    assert "Traceback" not in proc.stdout + proc.stderr
