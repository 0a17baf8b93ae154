"""The load tester as an operator runs it: a separate process against a real server on loopback."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import httpx
import numpy as np

from server import protocol as P
from server.client.loadtest import EncodedSequence
from tests.support.paths import REPO

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def run_loadtest(server, shared_data: Path, tmp_path: Path, *args: str):
    """The CLI on the first 12 frames of a real sequence (played back and forth) at 10 fps;
    returns the finished process and the JSON report."""
    report = tmp_path / "report.json"
    command = [
        sys.executable,
        "-m",
        "server",
        "loadtest",
        str(shared_data / "synthetic_room0"),
        "--url",
        server.url,
        "--frames",
        "12",
        "--fps",
        "10",
        "--json",
        str(report),
        *args,
    ]
    proc = subprocess.run(command, cwd=REPO, capture_output=True, text=True, timeout=120)
    assert report.is_file(), proc.stdout + proc.stderr
    return proc, json.loads(report.read_text())


def test_every_session_gets_poses_and_the_report_adds_up(live_server, shared_data, tmp_path):
    server = live_server()
    plot = tmp_path / "latency.png"
    proc, report = run_loadtest(
        server, shared_data, tmp_path, "--sessions", "2", "--duration", "4", "--plot", str(plot)
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "p95" in proc.stdout

    sessions = report["sessions"]
    assert len(sessions) == 2 and len({s["id"] for s in sessions}) == 2
    for s in sessions:
        assert s["processed"] > 5 and not s["failures"] and s["close_code"] == 1000
        assert s["sent"] + s["client_dropped"] == s["captured"] >= 35  # 4 s at 10 fps
        assert s["processed"] + s["server_dropped"] <= s["sent"]
        assert sum(s["states"].values()) == s["processed"]
        # Poses by recovery, as the server counted the frames in a segment.
        in_segment = s["server_status"]["recovery"]["in_segment"]
        assert s["recoveries"].get("segment", 0) == in_segment
        # The server counted the same frames as the client.
        assert s["server_status"]["frames_received"] == s["sent"]
        assert s["server_status"]["frames_processed"] == s["processed"]
        lat = s["latency"]
        assert 0 < lat["p50_ms"] <= lat["p95_ms"] <= lat["p99_ms"] <= lat["max_ms"]
        assert s["commands"]["sent"] >= 1
    total = report["total"]
    assert total["processed"] == sum(s["processed"] for s in sessions)
    assert total["processed"] + total["server_dropped"] <= total["sent"]
    assert 0 <= total["drop_rate"] <= 1 and total["failures"] == 0
    assert report["stages_ms"]["track"]["median"] > 0
    # The tracking thread's own CPU time is part of its wall time (the rest: waiting for a core).
    assert 0 < report["stages_ms"]["track_cpu"]["median"] <= report["stages_ms"]["track"]["median"]
    # One latency per pose, each pose answering a frame still in flight.
    assert [len(t) for t in report["timeline"]] == [s["processed"] for s in sessions]

    png = plot.read_bytes()
    assert png.startswith(PNG_SIGNATURE) and len(png) > 10_000
    # The sessions are deleted afterwards.
    assert httpx.get(f"{server.url}/healthz").json()["live_sessions"] == 0


def test_exit_status_is_non_zero_when_the_server_refuses_a_session(
    live_server, shared_data, tmp_path
):
    server = live_server(max_sessions=1)
    proc, report = run_loadtest(server, shared_data, tmp_path, "--sessions", "2", "--duration", "1")
    assert proc.returncode != 0
    assert "HTTP 503" in proc.stderr
    refused = [s for s in report["sessions"] if s["id"] is None]
    assert len(refused) == 1 and "HTTP 503" in refused[0]["failures"][0]
    assert report["total"]["failures"] == 1
    served = [s for s in report["sessions"] if s["id"] is not None]
    assert served[0]["processed"] > 0  # the other session ran as usual


def test_the_sequence_plays_back_and_forth_so_the_motion_stays_continuous():
    seq = EncodedSequence("four", (500.0, 500.0, 320.0, 240.0), (640, 480), [{}] * 4)
    assert [seq.index(k) for k in range(10)] == [0, 1, 2, 3, 2, 1, 0, 1, 2, 3]
    single = EncodedSequence("one", (500.0, 500.0, 320.0, 240.0), (640, 480), [{}])
    assert {single.index(k) for k in range(5)} == {0}


def test_sessions_start_spread_over_the_sequence_unless_in_lockstep():
    """Phones replaying one sequence are each elsewhere in it: every hard stretch would
    otherwise reach all of them at once."""
    seq = EncodedSequence("ten", (500.0, 500.0, 320.0, 240.0), (640, 480), [{}] * 10)
    starts = [seq.start(i, 4) for i in range(4)]  # one cycle is 18 captures: 0 1 .. 9 8 .. 1
    assert starts == [0, 4, 9, 13]
    assert [seq.index(k) for k in starts] == [0, 4, 9, 5]  # the last two play backward
    assert seq.start(0, 1) == 0
    single = EncodedSequence("one", (500.0, 500.0, 320.0, 240.0), (640, 480), [{}])
    assert {single.index(single.start(i, 3)) for i in range(3)} == {0}


def test_a_loop_correction_moves_the_drone_target_with_the_world():
    """After map_corrected the load tester's goto target (the drone's spawn point, kept in the
    old world) is moved by T_correction, as the server reads targets in the corrected world:
    kept as it was, it pointed into walls (11 targets unreachable in a 120 s run with loops)."""
    from server.client.loadtest.client import _Client
    from server.client.loadtest.results import LoadTestConfig

    client = _Client(0, None, LoadTestConfig(url="http://127.0.0.1:9"), None)  # no socket used
    client.spawn = [1.0, 0.0, 0.5]
    T = np.eye(4)
    T[:3, :3] = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]  # 90 deg about z
    T[:3, 3] = [0.0, 0.1, 0.0]
    client._handle(P.make_map_corrected(1, 40, T, [(3, 30, np.eye(4))], 0), None)
    assert np.allclose(client.spawn, [0.0, 1.1, 0.5])
    goto = [client._next_command() for _ in range(2)][1]
    assert goto["name"] == "goto" and np.allclose(goto["target"], [0.0, 1.1, 0.5])


def test_phone_profiles_send_the_frames_a_phone_sends_with_the_same_camera(shared_data):
    """`capacity.py --profile`: ARCore in live AR sends colour 640x288 (a 20:9 screen's crop)
    with depth 160x72, an iPhone recording 640x480 with LiDAR's 256x192; the intrinsics follow
    the crop and the scale, so a 3D point lands on the same scene pixel, and the frames decode
    at the sizes their hello announces."""
    from server.datasets import open_dataset

    ds = open_dataset(shared_data / "7scenes_a")
    K = ds.intrinsics
    point = np.array([0.21, -0.13, 1.7])  # camera frame, metres
    u0, v0 = K.fx * point[0] / point[2] + K.cx, K.fy * point[1] / point[2] + K.cy
    expected = {"kinect": ((640, 480), (640, 480)), "arcore": ((640, 288), (160, 72)),
                "iphone": ((640, 480), (256, 192))}  # fmt: skip
    for name, (colour_size, depth_size) in expected.items():
        seq = EncodedSequence.from_dataset(ds, max_frames=2, profile=name)
        assert (seq.size, seq.depth_size, seq.profile) == (colour_size, depth_size, name)
        fx, fy, cx, cy = seq.intrinsics
        u, v = fx * point[0] / point[2] + cx, fy * point[1] / point[2] + cy
        y0 = (480 - colour_size[1] * 640 / colour_size[0]) / 2  # the rows the crop left out
        assert abs(u - u0) < 1e-6 and abs(v - (v0 - y0)) < 1e-6, (name, u, v)
        hello = P.make_hello("t", seq.intrinsics, seq.size, seq.depth_size)
        colour, depth = P.decode_frame_images({**seq.frames[1], "seq": 0, "timestamp": 0.0}, hello)
        assert colour.shape[:2] == colour_size[::-1] and depth.shape[:2] == depth_size[::-1]
        # The depth is the colour's view: its centre reads the recording's centre (metres).
        recorded = ds[1].depth[240, 320]
        assert abs(float(depth[depth_size[1] // 2, depth_size[0] // 2]) - recorded) < 0.05
