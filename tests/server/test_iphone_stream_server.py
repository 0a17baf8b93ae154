"""The Python clients stream an iPhone recording with the phone's own pose in every frame.

The load tester (a separate process, as an operator runs it) plays a Record3D file, the replay
client a Stray export, both against a real server on loopback; the session's status says how
many frames carried T_device_camera and how many the tracker started from it. (The load tester's
encoded sequence: tests/unit/client/test_iphone_stream.py.)
"""

from __future__ import annotations

import asyncio
import json
import subprocess
import sys

import httpx
import numpy as np
import pytest

from server import protocol as P
from server.client.replay import replay
from server.datasets import open_dataset
from tests.conftest import auth
from tests.support.iphone_recordings import room_recording, write_r3d, write_stray
from tests.support.paths import REPO, SHARED_DATA

ROOM = SHARED_DATA / "synthetic_room0"
pytestmark = pytest.mark.skipif(not ROOM.is_dir(), reason=f"shared data not found at {ROOM}")

FRAMES = 16


@pytest.fixture(scope="module")
def room():
    return room_recording(ROOM, list(range(0, 2 * FRAMES, 2)))  # every other frame: 15 fps


def test_the_load_test_sends_a_record3d_recordings_device_poses(live_server, room, tmp_path):
    r3d = write_r3d(room, tmp_path / "scan.r3d")
    server = live_server()
    report_path = tmp_path / "report.json"
    command = [
        sys.executable,
        "-m",
        "server",
        "loadtest",
        str(r3d),
        "--url",
        server.url,
        "--sessions",
        "1",
        "--fps",
        "10",
        "--duration",
        "3",
        "--command-every",
        "0",
        "--json",
        str(report_path),
    ]
    proc = subprocess.run(command, cwd=REPO, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    (session,) = json.loads(report_path.read_text())["sessions"]
    status = session["server_status"]
    assert status["frames_processed"] == session["processed"] >= 10
    use = status["device_pose"]
    assert use["frames"] == status["frames_processed"]
    # Played back and forth, the phone's motion stays continuous: every frame after the first
    # starts from it.
    assert use["guesses"] == use["frames"] - 1
    assert session["states"].get("lost", 0) == 0


def test_replay_of_a_stray_export_sends_its_device_poses(live_server, room, tmp_path):
    ds = open_dataset(write_stray(room, tmp_path / "scan"))
    server = live_server()
    sid, token = server.create_session()
    stats = asyncio.run(
        replay(
            f"{server.ws_url}/ws/sessions/{sid}",
            token,
            ds,
            fps=1000,
            max_in_flight=1,
            drop_when_busy=False,
        )
    )
    assert stats.completed, stats.failure
    assert stats.sent == stats.answered == FRAMES
    status = httpx.get(f"{server.url}/api/sessions/{sid}", headers=auth(token)).json()
    assert status["device_pose"] == {"frames": FRAMES, "guesses": FRAMES - 1, "world_changes": 0}
    # Poses are in the map (the first camera's frame), following the phone's motion.
    est = np.array([P.pose_matrix(p) for p in stats.poses])
    rel_phone = np.linalg.inv(ds.device_poses.poses[0]) @ ds.device_poses.poses[-1]
    np.testing.assert_allclose(est[0], np.eye(4), atol=1e-6)
    assert np.linalg.norm(est[-1][:3, 3] - rel_phone[:3, 3]) < 0.02
