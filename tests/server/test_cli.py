"""The command line, run as a user would: a separate process, real files."""

from __future__ import annotations

import json

import numpy as np
import open3d as o3d
import pytest

from server.config import load_config
from server.evaluation.trajectory import read_tum
from tests.support.cli import run_cli


def test_track_writes_trajectory_map_picture_and_metrics(shared_data, tmp_path):
    out = tmp_path / "out"
    proc = run_cli(
        "track", str(shared_data / "synthetic_room0"), "--frames", "8", "--out", str(out)
    )
    assert proc.returncode == 0, proc.stderr
    out = out / "latest"  # the run's own folder
    traj = read_tum(out / "trajectory.tum")
    assert len(traj) == 8  # one pose per input frame
    assert np.isfinite(traj.poses).all()
    ply = (out / "map.ply").read_bytes()
    assert ply.startswith(b"ply\nformat binary_little_endian")
    assert b"property uchar red" in ply
    png = (out / "trajectory.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000
    assert "ATE" in proc.stdout


def test_each_track_run_gets_its_own_folder_latest_names_it_and_room_continues_it(
    shared_data, tmp_path
):
    """Two runs into one --out: two folders, ``latest`` at the second, which continued in the
    first's room by naming --out alone; --mesh wrote the upright mesh (z-up PLY, y-up GLB)."""
    from evo.tools import file_interface

    from tests.support.glb import accessor, read_glb

    seq, out = str(shared_data / "synthetic_room0"), tmp_path / "out"
    proc = run_cli("track", seq, "--frames", "8", "--out", str(out), "--mesh")
    assert proc.returncode == 0, proc.stderr
    first = (out / "latest").resolve()
    assert first.parent == out and first.name.startswith("synthetic_room0_")
    proc = run_cli(
        "track", seq, "--frames", "5", "--out", str(out), "--room", str(out), "--no-save-room"
    )
    assert proc.returncode == 0, proc.stderr
    second = (out / "latest").resolve()
    assert sorted(p.name for p in out.iterdir()) == sorted(["latest", first.name, second.name])
    assert json.loads((second / "summary.json").read_text())["relocalisation"]["relocalised"]
    assert not (second / "room").exists() and not (second / "mesh.ply").exists()
    # evo reads the trajectory as it is written.
    assert file_interface.read_tum_trajectory_file(out / "latest" / "trajectory.tum").num_poses == 5

    summary = json.loads((first / "summary.json").read_text())
    R = np.array(summary["upright"]["R_upright_world"])
    assert summary["upright"]["source"] in ("surfaces", "camera")
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-9)
    ply = o3d.io.read_triangle_mesh(str(first / "mesh.ply"))
    z_up = np.asarray(ply.vertices)
    assert len(ply.triangles) > 1000 and ply.has_vertex_colors()
    document, blob = read_glb((first / "mesh.glb").read_bytes())
    primitive = document["meshes"][0]["primitives"][0]
    y_up = accessor(document, blob, primitive["attributes"]["POSITION"])
    np.testing.assert_allclose(y_up, z_up[:, [1, 2, 0]], atol=1e-5)  # the same mesh, y up
    assert len(accessor(document, blob, primitive["indices"])) == 3 * len(ply.triangles)
    # Upright: the first camera's up (-y) points up in the PLY, within a tilted hand's angle.
    camera_up = read_tum(first / "trajectory.tum").poses[0][:3, :3] @ [0, -1.0, 0]
    assert (R @ camera_up)[2] > np.cos(np.radians(50))


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
    first = first / "latest"
    written = load_config(first / "config.yaml")
    assert written.registration.keyframes.max_rotation_deg == 10.0
    assert written.registration.solver.dense is False
    proc = run_cli(
        "track", room, "--frames", "5", "--out", str(second),
        "--config", str(first / "config.yaml"),
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    second = second / "latest"
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


def test_evaluate_aligns_as_asked_and_writes_json_and_a_picture(tmp_path):
    """An estimate that is the ground truth under a Sim(3) (scale 1.2) with 1 cm of noise: sim3
    alignment finds the noise alone, se3 leaves the scale's error, none the whole offset. The
    JSON holds what the table shows; --delta in frames changes the second RPE; bad choices are
    refused."""
    from server.evaluation.trajectory import Trajectory, write_tum
    from server.geometry.se3 import exp_se3 as se3_exp

    rng = np.random.default_rng(3)
    n = 200
    t = np.linspace(0, 2 * np.pi, n)
    poses = np.stack([se3_exp(np.array([np.cos(a), np.sin(a), 0.1 * a, 0, 0, a])) for a in t])
    gt = Trajectory(np.arange(n) / 30.0, poses)
    S = se3_exp(np.array([0.5, -0.2, 1.0, 0.1, 0.3, -0.2]))
    est_poses = S @ poses
    est_poses[:, :3, 3] = 1.2 * est_poses[:, :3, 3] + rng.normal(0, 0.01, (n, 3))
    write_tum(tmp_path / "gt.tum", gt)
    write_tum(tmp_path / "est.tum", Trajectory(gt.timestamps.copy(), est_poses))
    ate = {}
    for align in ("sim3", "se3", "none"):
        out = tmp_path / f"{align}.json"
        args = ["evaluate", str(tmp_path / "gt.tum"), str(tmp_path / "est.tum"), "--align", align]
        proc = run_cli(*args, "--json", str(out), "--plot", str(tmp_path / f"{align}.png"))
        assert proc.returncode == 0, proc.stderr
        report = json.loads(out.read_text())
        assert report["align"] == align and report["matched"] == n
        ate[align] = report["ate_rmse_m"]
        assert (tmp_path / f"{align}.png").stat().st_size > 10_000
    assert ate["sim3"] < 0.02 < 0.1 < ate["se3"] < ate["none"], ate
    frames = run_cli(
        "evaluate",
        str(tmp_path / "gt.tum"),
        str(tmp_path / "est.tum"),
        "--delta",
        "10",
        "--delta-unit",
        "frames",
        "--json",
        str(tmp_path / "d.json"),
    )
    assert frames.returncode == 0, frames.stderr
    by_frames = json.loads((tmp_path / "d.json").read_text())
    assert by_frames["rpe_delta"] == {"value": 10.0, "unit": "frames"}
    assert (
        by_frames["rpe_trans_per_second_m"]
        != json.loads((tmp_path / "se3.json").read_text())["rpe_trans_per_second_m"]
    )
    bad = run_cli("evaluate", str(tmp_path / "gt.tum"), str(tmp_path / "gt.tum"), "--align", "x")
    assert bad.returncode != 0 and "--align must be one of" in bad.stderr
