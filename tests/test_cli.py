"""The command line, run as a user would: a separate process, real files."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from server.config import load_config
from server.evaluation.trajectory import read_tum

REPO = Path(__file__).resolve().parents[1]


def run_cli(
    *args: str, env: dict | None = None, timeout: float = 300
) -> subprocess.CompletedProcess:
    # The configuration comes from the arguments alone (the demo's cache location may stay).
    clean = {
        k: v
        for k, v in os.environ.items()
        if not k.upper().startswith("DRONESIM_") or k.upper() == "DRONESIM_CACHE"
    }
    return subprocess.run(
        [sys.executable, "-m", "server", *args],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=timeout,
        env={**clean, **(env or {})},
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


# ---- the configuration --------------------------------------------------------------------------


def test_track_takes_set_and_writes_the_configuration_that_reproduces_the_run(
    shared_data, tmp_path
):
    room = str(shared_data / "synthetic_room0")
    first, second = tmp_path / "first", tmp_path / "second"
    proc = run_cli(
        "track", room, "--frames", "5", "--out", str(first), "--no-dense",
        "--set", "registration.keyframes.max_rotation_deg=10",
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert "max_rotation_deg: 10.0" in proc.stdout  # the effective configuration, printed
    written = load_config(first / "config.yaml")
    assert written.registration.keyframes.max_rotation_deg == 10.0
    assert written.registration.solver.dense is False
    proc = run_cli(
        "track", room, "--frames", "5", "--out", str(second),
        "--config", str(first / "config.yaml"),
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert load_config(second / "config.yaml") == written
    a, b = read_tum(first / "trajectory.tum"), read_tum(second / "trajectory.tum")
    np.testing.assert_allclose(a.poses, b.poses, atol=1e-9)


def test_a_bad_key_stops_track_before_it_starts_naming_the_key(tmp_path):
    out = tmp_path / "o"
    proc = run_cli("track", "demo", "--out", str(out), "--set", "registration.keyframe.x=1")
    assert proc.returncode == 1
    assert "registration.keyframe: unknown key" in proc.stderr
    assert "Traceback" not in proc.stdout + proc.stderr
    assert not out.exists()


def test_config_prints_the_effective_configuration_as_a_file_reads_it(tmp_path):
    proc = run_cli("config", "--set", "mapping.fuse_every=5", env={
        "DRONESIM_REGISTRATION__SOLVER__DENSE": "false", "DRONESIM_PORT": "9001"
    })  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    path = tmp_path / "printed.yaml"
    path.write_text(proc.stdout)
    config = load_config(path)
    assert config.mapping.fuse_every == 5
    assert config.registration.solver.dense is False and config.server.port == 9001


@pytest.mark.parametrize(
    "args, env, named",
    [
        (["--set", "server.port=0"], {}, "server.port"),
        ([], {"DRONESIM_REGISTRATION__SOLVER__NOSUCH": "1"}, "registration.solver.nosuch"),
        ([], {"DRONESIM_PREVIEW_POINTS": "20000"}, "mapping.preview_points"),
    ],
)
def test_a_bad_configuration_stops_serve_before_it_starts(tmp_path, args, env, named):
    data = tmp_path / "data"
    proc = run_cli("serve", "--data-dir", str(data), *args, env=env, timeout=60)
    assert proc.returncode == 1
    assert named in proc.stderr and "Traceback" not in proc.stderr
    assert not data.exists()


def test_serve_prints_its_configuration_and_hands_it_to_the_sessions(tmp_path):
    from server.client.server_process import ServerProcess

    log = tmp_path / "server.log"
    env = {
        "DRONESIM_MAPPING__TSDF__VOXEL_M": "0.03",
        "DRONESIM_REGISTRATION__KEYFRAMES__MAX_ROTATION_DEG": "12",
        "DRONESIM_ALLOCATOR": "system",
    }
    server = ServerProcess(tmp_path / "data", env, log=log)
    try:
        sid, _ = server.create_session()
        meta = json.loads((tmp_path / "data" / "sessions" / sid / "meta.json").read_text())
        assert meta["voxel_m"] == 0.03  # written by the session's own worker process
        server.terminate()  # SIGTERM: saves the session and ends its worker
    finally:
        server.stop()
    text = log.read_text()
    assert "max_rotation_deg: 12.0" in text and "voxel_m: 0.03" in text


def test_version_and_every_option_is_explained():
    """`--version` prints pyproject's version; every option of every command has help text, and
    no help shows reST's double backticks (the help is rendered as Markdown)."""
    import typer.main

    from server import __version__
    from server.cli import app

    result = run_cli("--version")
    assert result.returncode == 0 and result.stdout.strip() == f"dronesim-ar {__version__}"
    group = typer.main.get_command(app)
    unexplained = []
    for name, command in group.commands.items():  # type: ignore[attr-defined]
        assert command.help and "``" not in command.help, name
        for param in command.params:
            if param.param_type_name == "option" and param.name != "help":
                if not (param.help or "").strip():
                    unexplained.append(f"{name} {param.opts[0]}")
    assert not unexplained, f"options without help: {unexplained}"
