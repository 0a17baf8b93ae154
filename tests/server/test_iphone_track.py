"""``track`` on an iPhone recording uses the phone's own odometry as the tracker's prior.

The recording is synthetic_room0 with bursts of frames missing (as when the phone's recorder
stalls), and odometry that drifts as a phone's does (server.evaluation.device_poses), in a world
of its own. Without the prior the bursts lose tracking; with it the trajectory stays on the
ground truth.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from server.datasets import open_dataset
from server.evaluation.device_poses import drifting_device_poses
from server.evaluation.metrics import associate_trajectories, ate
from server.evaluation.trajectory import Trajectory
from server.pipeline import run_odometry
from server.registration.config import RegistrationConfig
from tests.support.iphone_recordings import room_recording, write_stray
from tests.support.paths import REPO, SHARED_DATA

ROOM = SHARED_DATA / "synthetic_room0"
pytestmark = pytest.mark.skipif(not ROOM.is_dir(), reason=f"shared data not found at {ROOM}")

BURST = 15  # frames missing in a row, after every 3 * BURST recorded
KEPT = [i for i in range(120) if i % (4 * BURST) < 3 * BURST]  # two bursts missing


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> tuple[Path, np.ndarray]:
    """A Stray export with bursts missing and drifting odometry; and its ground truth."""
    room = room_recording(ROOM, KEPT)
    room["poses"] = drifting_device_poses(room["ground_truth"], room["timestamps"])
    folder = write_stray(room, tmp_path_factory.mktemp("stray") / "bursts")
    return folder, room["ground_truth"]


def ate_rmse(ds, trajectory: Trajectory, ground_truth: np.ndarray) -> float:
    gt, est = associate_trajectories(Trajectory(ds.timestamps, ground_truth), trajectory)
    assert len(gt) == len(ds)
    return float(ate(gt, est)["rmse"])


def test_the_recordings_odometry_carries_tracking_over_missing_frames(recording):
    folder, ground_truth = recording
    ds = open_dataset(folder)
    assert ds.device_poses is not None and len(ds) == len(KEPT)

    with_prior = run_odometry(ds, progress=False)
    assert with_prior.summary["device_prior"]["frames"] == len(KEPT)
    # Every frame after the first started from the phone's motion.
    assert with_prior.summary["device_prior"]["guesses"] == len(KEPT) - 1
    assert with_prior.summary["states"].get("lost", 0) == 0, with_prior.summary["states"]
    # The odometry drifts 3 % of the path and its heading; the tracker stays within 1 cm.
    assert ate_rmse(ds, with_prior.trajectory, ground_truth) < 0.01

    # Flow alone (no prior, no place recognition) loses track over the bursts.
    off = RegistrationConfig().with_overrides(
        prior={"enabled": False}, relocalise={"enabled": False}
    )
    without = run_odometry(ds, off, progress=False)
    assert without.summary["device_prior"] == {"frames": 0, "guesses": 0}
    assert without.summary["states"].get("lost", 0) > 0, "the bursts no longer lose tracking"
    # Off means as before: exactly the run of a dataset that has no device poses (the prior
    # left on, place recognition off as above).
    ds.device_poses = None
    plain = run_odometry(
        ds, RegistrationConfig().with_overrides(relocalise={"enabled": False}), progress=False
    )
    np.testing.assert_array_equal(plain.trajectory.poses, without.trajectory.poses)


def track_command(folder: Path, out: Path, *flags: str) -> dict:
    env = {k: v for k, v in os.environ.items() if not k.upper().startswith("DRONESIM_")}
    proc = subprocess.run(
        [sys.executable, "-m", "server", "track", str(folder), "--frames", "12", "--out", str(out)]
        + list(flags),
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    run = out / "latest"  # the run's own folder under --out
    summary = json.loads((run / "summary.json").read_text())
    summary["stdout"] = proc.stdout
    summary["config_file"] = yaml.safe_load((run / "config.yaml").read_text())
    return summary


def test_track_command_uses_the_prior_unless_told_not_to(recording, tmp_path):
    folder, _ = recording
    on = track_command(folder, tmp_path / "on")
    assert on["device_prior"] == {"frames": 12, "guesses": 11}
    assert "12 frames carried the recording's odometry" in on["stdout"]
    off = track_command(folder, tmp_path / "off", "--no-device-prior")
    assert off["device_prior"] == {"frames": 0, "guesses": 0}
    assert "device prior: off" in off["stdout"]
    # The switch is the configuration key, written out so that the run can be repeated.
    assert off["config_file"]["registration"]["prior"]["enabled"] is False
