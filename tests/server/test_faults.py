"""Faults: a killed or stopped server, a client that drops off and comes back (or never does),
and a camera that sees nothing trackable. Nothing a session built may be lost or half-written.

The kill tests run ``python -m server serve`` as a subprocess (a signal must hit a whole
server); the others use the in-process ``live_server`` fixture.
"""

from __future__ import annotations

import asyncio
import json
import os
import shutil
import signal
import time
from pathlib import Path

import httpx
import numpy as np
import open3d as o3d
import pytest
import websockets

from server import protocol as P
from server.client.connection import Socket
from server.client.server_process import ServerProcess
from server.datasets import open_dataset
from server.evaluation.trajectory import read_tum
from server.mapping.tsdf import TSDFMap
from tests.conftest import Stream, auth, offline_track, session_status
from tests.support.rest import map_caught_up, wait_for_status


@pytest.fixture
def server_process(tmp_path):
    started = []

    def start(data_dir: Path, **settings) -> ServerProcess:
        env = {f"DRONESIM_{k.upper()}": str(v) for k, v in settings.items()}
        server = ServerProcess(data_dir, env, log=tmp_path / f"server{len(started)}.log")
        started.append(server)
        return server

    yield start
    for server in started:
        server.stop()


@pytest.fixture(scope="module")
def room(shared_data):
    return open_dataset(shared_data / "synthetic_room0")


def assert_session_files_whole(folder: Path) -> dict:
    """Every file of a saved session parses; no temp file of an interrupted write is left."""
    names = sorted(p.name for p in folder.iterdir())
    assert not [n for n in names if n.startswith(".")], names
    meta = json.loads((folder / "meta.json").read_text())
    trajectory = read_tum(folder / "trajectory.tum")
    cloud = o3d.io.read_point_cloud(str(folder / "map.ply"))
    assert len(cloud.points) > 1000 and cloud.has_colors()
    assert TSDFMap.load(folder / "map.npz").stats()["frames_integrated"] > 0
    return {"meta": meta, "trajectory": trajectory, "map_points": len(cloud.points)}


def snapshot_with_poses(folder: Path, at_least: int) -> bool:
    """A committed snapshot is on disk with a map and ``at_least`` poses in its trajectory."""
    try:
        lines = (folder / "trajectory.tum").read_text().splitlines()
    except FileNotFoundError:
        return False
    poses = [line for line in lines if line.strip() and not line.startswith("#")]
    return (folder / "map.ply").is_file() and len(poses) >= at_least


# ---- the server dies ---------------------------------------------------------------------------


def test_after_sigkill_mid_session_the_last_snapshot_is_whole_and_downloadable(
    server_process, room, tmp_path
):
    data_dir = tmp_path / "data"
    server = server_process(data_dir, snapshot_interval_s=1.0)
    sid, token = server.create_session()
    folder = data_dir / "sessions" / sid
    stream = Stream(server.ws_url, sid, token, room)

    async def stream_then_kill():
        await stream.open()
        await stream.send_range(range(15))
        # Until a committed snapshot holds a map and all of those 15 poses: on a busy machine the
        # first snapshot can land after only a dozen frames, and a kill right after it would
        # leave too few to check the order against.
        deadline = time.monotonic() + 60
        seq = 15
        while not snapshot_with_poses(folder, 15) and time.monotonic() < deadline:
            await stream.send(seq)
            seq += 1
        await stream.send_range(range(seq, seq + 10))
        f = room[seq + 10]  # one more in flight as the server dies
        await stream.conn.send_frame(P.make_frame(seq + 10, f.timestamp, f.colour, f.depth))
        assert server.signal(signal.SIGKILL) == -signal.SIGKILL

    asyncio.run(stream_then_kill())
    received = stream.matrices()
    (folder / ".map.npz.k1ll3d.npz").write_bytes(b"PK\x03\x04 half a zip")  # a write cut short
    (folder / ".snapshot").mkdir(exist_ok=True)  # a snapshot staged, never committed
    (folder / ".snapshot" / "trajectory.tum").write_text("# newer than the committed one\n")

    again = server_process(data_dir)
    saved = assert_session_files_whole(folder)
    n = len(saved["trajectory"])
    assert 15 <= n <= len(received)
    # The snapshot's poses are the ones the client was sent, in order (9 decimals on disk).
    np.testing.assert_allclose(saved["trajectory"].poses[:, :3, 3], received[:n, :3, 3], atol=1e-6)
    status = session_status(again.url, sid, token)
    assert status["closed"] is True and n <= status["frames_processed"] <= len(received)
    tum = httpx.get(f"{again.url}/api/sessions/{sid}/trajectory.tum", headers=auth(token))
    assert tum.status_code == 200 and tum.content == (folder / "trajectory.tum").read_bytes()
    ply = httpx.get(f"{again.url}/api/sessions/{sid}/map.ply", headers=auth(token), timeout=60)
    assert ply.status_code == 200 and ply.content == (folder / "map.ply").read_bytes()
    mesh = httpx.get(f"{again.url}/api/sessions/{sid}/mesh.ply", headers=auth(token), timeout=60)
    assert mesh.status_code == 200 and mesh.content.startswith(b"ply")
    assert "partial files of an interrupted write" in again.log.read_text()


def test_sigterm_saves_every_processed_frame_before_exiting(server_process, room, tmp_path):
    data_dir = tmp_path / "data"
    server = server_process(data_dir, snapshot_interval_s=3600)  # only the shutdown saves
    sid, token = server.create_session()
    stream = Stream(server.ws_url, sid, token, room)

    async def stream_then_terminate():
        await stream.open()
        await stream.send_range(range(25))
        terminated = asyncio.create_task(asyncio.to_thread(server.signal, signal.SIGTERM))
        error = await stream.answer()  # the server says why before it closes
        with pytest.raises(websockets.ConnectionClosed) as closed:
            await stream.answer()
        return await terminated, error, closed.value.rcvd.code

    code, error, close_code = asyncio.run(stream_then_terminate())
    assert code in (0, -signal.SIGTERM)  # uvicorn re-raises the signal after a clean shutdown
    assert error["type"] == "error" and error["name"] == "server_shutdown", error
    assert "saved" in error["message"]
    assert close_code == P.CLOSE_CODES["server_shutdown"]
    log = server.log.read_text()
    assert "Application shutdown complete" in log and "Traceback" not in log
    assert token not in log  # uvicorn logs the WebSocket path: the token is redacted
    saved = assert_session_files_whole(data_dir / "sessions" / sid)
    assert saved["meta"]["closed"] is True and saved["meta"]["status"]["frames_processed"] == 25
    assert len(saved["trajectory"]) == 25
    np.testing.assert_allclose(
        saved["trajectory"].poses[:, :3, 3], stream.matrices()[:, :3, 3], atol=1e-6
    )


# ---- a session's worker dies --------------------------------------------------------------------


def test_a_crashed_worker_is_reported_and_its_session_kept_as_its_last_snapshot(live_server, room):
    """SIGKILL one session's worker process (as a native crash or the OOM killer would): its
    client gets session_failed and close 4010 at once (never a hung socket); the session is
    closed, downloadable as its last snapshot left it; the neighbour session goes on."""
    server = live_server(snapshot_interval_s=1.0)
    sid, token = server.create_session()
    other_sid, other_token = server.create_session()
    folder = server.settings.data_dir / "sessions" / sid
    stream = Stream(server.ws_url, sid, token, room)
    neighbour = Stream(server.ws_url, other_sid, other_token, room)

    async def stream_then_crash():
        await stream.open()
        await neighbour.open()
        await neighbour.send_range(range(5))
        seq, deadline = 0, time.monotonic() + 60
        while not (folder / "map.ply").is_file() and time.monotonic() < deadline:
            await stream.send(seq)  # until a snapshot with a map is on disk
            seq += 1
        await stream.send_range(range(seq, seq + 3))
        pid = session_status(server.url, sid, token)["worker"]["pid"]
        assert pid != session_status(server.url, other_sid, other_token)["worker"]["pid"]
        os.kill(pid, signal.SIGKILL)
        error = await stream.answer()
        with pytest.raises(websockets.ConnectionClosed) as closed:
            await stream.answer()
        await neighbour.send_range(range(5, 10))  # the other session never noticed
        return error, closed.value.rcvd.code

    started = time.monotonic()
    error, close_code = asyncio.run(stream_then_crash())
    assert time.monotonic() - started < 90
    assert error["type"] == "error" and error["name"] == "session_failed", error
    assert "SIGKILL" in error["message"] and "last snapshot" in error["message"]
    assert close_code == P.CLOSE_CODES["session_failed"]
    assert len(neighbour.poses) == 10
    status = session_status(server.url, sid, token)
    assert status["closed"] is True and "SIGKILL" in status["failure"]
    saved = assert_session_files_whole(folder)
    assert 0 < len(saved["trajectory"]) <= len(stream.poses)
    assert saved["meta"]["closed"] is True
    ply = httpx.get(f"{server.url}/api/sessions/{sid}/map.ply", headers=auth(token), timeout=60)
    assert ply.status_code == 200 and ply.content == (folder / "map.ply").read_bytes()

    async def come_back():  # the session is closed: a new socket is refused, not hung
        async with await Socket.connect(f"{server.ws_url}/ws/sessions/{sid}", token) as socket:
            msg = await socket.receive(30)
            with pytest.raises(websockets.ConnectionClosed) as closed:
                await socket.receive(30)
            return msg, closed.value.rcvd.code

    msg, code = asyncio.run(come_back())
    assert msg["name"] == "unauthorized" and code == P.CLOSE_CODES["unauthorized"]


# ---- the client drops off ----------------------------------------------------------------------


def test_a_client_that_drops_off_and_returns_within_the_ttl_continues_its_session(
    live_server, room
):
    server = live_server(session_ttl_s=30)
    sid, token = server.create_session()
    stream = Stream(server.ws_url, sid, token, room)

    def status() -> dict:
        return session_status(server.url, sid, token)

    async def drop_and_return():
        await stream.open()
        await stream.send_range(range(15))
        points_before = stream.map_points
        stream.abort()
        await asyncio.sleep(0.5)
        before = status()
        await stream.open()  # same token, same camera
        await stream.send_range(range(15, 30))
        await stream.conn.bye("done")
        return before, points_before

    before, points_before = asyncio.run(drop_and_return())
    assert before["closed"] is False and before["frames_processed"] == 15
    after = status()
    assert after["closed"] is False and after["frames_processed"] == 30
    assert after["map"]["frames_integrated"] > before["map"]["frames_integrated"] > 0
    # The map grew after the return (its preview may still lag the poses at the drop).
    assert stream.map_points > points_before
    # One trajectory across both sockets, as if the phone had never left.
    np.testing.assert_allclose(
        stream.matrices()[:, :3, 3], offline_track(room, 30)[:, :3, 3], atol=1e-6
    )
    tum = httpx.get(f"{server.url}/api/sessions/{sid}/trajectory.tum", headers=auth(token))
    assert len(tum.text.strip().splitlines()) == 1 + 30  # header line + poses


def test_a_phone_back_from_a_silent_wifi_drop_takes_its_session_over_at_once(live_server, room):
    """The old socket never closed (no FIN reached the server), so the server still holds it:
    the phone's new socket with the token takes the session over instead of waiting out the
    idle timeout; the old one is told why, and a stranger's socket takes nothing."""
    server = live_server()
    sid, token = server.create_session()
    phone = Stream(server.ws_url, sid, token, room)

    async def drop_silently_and_return():
        await phone.open()
        await phone.send_range(range(10))
        stale = phone.conn  # left open and unread: what the server sees of a phone off the Wi-Fi
        wrong = ("y" if token[0] == "x" else "x") + token[1:]
        async with await Socket.connect(f"{server.ws_url}/ws/sessions/{sid}", wrong) as stranger:
            refused = await stranger.receive(10)
        t0 = time.monotonic()
        await phone.open()
        took_over_s = time.monotonic() - t0
        await phone.send_range(range(10, 20))  # numbered on, as a page that kept its state
        told = await stale.until_closed(10)
        await phone.conn.bye("done")
        return refused, took_over_s, told, stale.close_code

    refused, took_over_s, told, old_code = asyncio.run(drop_silently_and_return())
    assert refused["name"] == "unauthorized"
    assert took_over_s < 5.0 < P.LIMITS["idle_timeout_s"]
    errors = [m for m in told if m["type"] == "error"]
    assert [e["name"] for e in errors] == ["session_taken_over"]
    assert old_code == P.CLOSE_CODES["session_taken_over"]
    status = session_status(server.url, sid, token)
    assert status["closed"] is False and status["frames_processed"] == 20
    np.testing.assert_allclose(
        phone.matrices()[:, :3, 3], offline_track(room, 20)[:, :3, 3], atol=1e-6
    )


def test_deleting_a_connected_session_tells_its_socket_and_closes_it(live_server, room):
    server = live_server()
    sid, token = server.create_session()
    phone = Stream(server.ws_url, sid, token, room)

    async def stream_then_delete():
        await phone.open()
        await phone.send_range(range(5))
        deleted = await asyncio.to_thread(
            httpx.delete, f"{server.url}/api/sessions/{sid}", headers=auth(token), timeout=60
        )
        told = await phone.conn.until_closed(10)
        return deleted.status_code, told, phone.conn.close_code

    code, told, close_code = asyncio.run(stream_then_delete())
    assert code == 204
    errors = [m for m in told if m["type"] == "error"]
    assert [(e["name"], e["message"]) for e in errors] == [
        ("unauthorized", "this session was deleted")
    ]
    assert close_code == P.CLOSE_CODES["unauthorized"]
    assert httpx.get(f"{server.url}/api/sessions/{sid}", headers=auth(token)).status_code == 404
    assert not (server.settings.data_dir / "sessions" / sid).exists()


def test_a_client_that_never_returns_is_closed_and_saved_after_the_ttl(live_server, room):
    server = live_server(session_ttl_s=1.0)
    sid, token = server.create_session()
    stream = Stream(server.ws_url, sid, token, room)

    async def stream_and_vanish():
        await stream.open()
        await stream.send_range(range(12))
        stream.abort()

    asyncio.run(stream_and_vanish())
    deadline = time.monotonic() + 30
    while httpx.get(f"{server.url}/healthz").json()["live_sessions"] and (
        time.monotonic() < deadline
    ):
        # While it closes, its owner still finds it (marked closed), never a 404.
        r = httpx.get(f"{server.url}/api/sessions/{sid}", headers=auth(token))
        assert r.status_code == 200, r.text
        time.sleep(0.1)
    status = session_status(server.url, sid, token)
    assert status["closed"] is True and status["frames_processed"] == 12
    saved = assert_session_files_whole(server.settings.data_dir / "sessions" / sid)
    assert len(saved["trajectory"]) == 12 and saved["meta"]["closed"] is True

    async def come_back_too_late():
        async with await Socket.connect(f"{server.ws_url}/ws/sessions/{sid}", token) as socket:
            msg = await socket.receive(30)
            with pytest.raises(websockets.ConnectionClosed) as closed:
                await socket.receive(30)
            return msg, closed.value.rcvd.code

    msg, code = asyncio.run(come_back_too_late())
    assert msg["name"] == "unauthorized" and "closed" in msg["message"]
    assert code == P.CLOSE_CODES["unauthorized"]
    ply = httpx.get(f"{server.url}/api/sessions/{sid}/map.ply", headers=auth(token), timeout=60)
    assert ply.status_code == 200 and ply.content.startswith(b"ply")


def test_a_session_that_cannot_be_saved_stays_in_memory_until_the_disk_takes_it(live_server, room):
    """The disk refuses the map (here a folder sits where map.npz must go; for root, who ignores
    permissions, the closest to a full disk). Closing after the TTL must not drop the session:
    it stays live, closed to frames, downloadable from memory, says why, and is saved as soon
    as the disk takes it."""
    server = live_server(session_ttl_s=1.0)
    sid, token = server.create_session()
    folder = server.settings.data_dir / "sessions" / sid
    (folder / "map.npz" / "in-the-way").mkdir(parents=True)

    async def stream_and_vanish():
        stream = Stream(server.ws_url, sid, token, room)
        await stream.open()
        await stream.send_range(range(12))
        stream.abort()

    asyncio.run(stream_and_vanish())
    # The TTL passes, then the close is tried and fails: closed (its stop has ended), not saved.
    # (A periodic snapshot may have failed before, setting snapshot_error while still live.)
    deadline = time.monotonic() + 30
    while not (status := session_status(server.url, sid, token))["closed"]:
        assert time.monotonic() < deadline, "the close after the TTL was never tried"
        time.sleep(0.1)
    assert httpx.get(f"{server.url}/healthz").json()["live_sessions"] == 1
    assert status["closed"] is True and status["frames_processed"] == 12
    assert "IsADirectoryError" in status["snapshot_error"]
    ply = httpx.get(f"{server.url}/api/sessions/{sid}/map.ply", headers=auth(token), timeout=60)
    assert ply.status_code == 200 and ply.content.startswith(b"ply")  # from memory

    shutil.rmtree(folder / "map.npz")  # the disk is back
    deadline = time.monotonic() + 30
    while httpx.get(f"{server.url}/healthz").json()["live_sessions"]:
        assert time.monotonic() < deadline, "the session was never saved"
        time.sleep(0.1)
    saved = assert_session_files_whole(folder)
    assert len(saved["trajectory"]) == 12 and saved["meta"]["closed"] is True
    assert saved["meta"]["status"]["snapshot_error"] is None


# ---- the camera sees nothing trackable ---------------------------------------------------------


def test_a_session_lost_for_long_keeps_its_map_and_says_so(live_server, room):
    server = live_server()
    sid, token = server.create_session()
    stream = Stream(server.ws_url, sid, token, room)
    K = room.intrinsics
    wall_colour = np.full((K.height, K.width, 3), 128, np.uint8)  # a blank wall...
    wall_depth = np.full((K.height, K.width), 1.2, np.float32)  # ...as a constant depth plane

    def settled_status() -> dict:
        """Status once the mapping thread has fused every frame it will of those sent (it runs
        behind the poses, by seconds on a busy machine): its map figures are then final."""
        return wait_for_status(server.url, sid, token, map_caught_up, "the map to catch up")

    def map_ply() -> o3d.geometry.PointCloud:
        r = httpx.get(f"{server.url}/api/sessions/{sid}/map.ply", headers=auth(token), timeout=60)
        path = server.settings.data_dir / "download.ply"
        path.write_bytes(r.content)
        return o3d.io.read_point_cloud(str(path))

    async def go():
        await stream.open()
        await stream.send_range(range(20))
        good = await asyncio.to_thread(settled_status)
        cloud_before = await asyncio.to_thread(map_ply)
        for seq in range(20, 60):
            await stream.send(seq, wall_colour, wall_depth)
        lost = await asyncio.to_thread(settled_status)
        cloud_after = await asyncio.to_thread(map_ply)
        for k, seq in enumerate(range(60, 65)):  # the room again, where the camera left it
            await stream.send(seq, index=20 + k)
        return good, lost, cloud_before, cloud_after

    good, lost, cloud_before, cloud_after = asyncio.run(go())
    assert not good["tracking_lost"]
    states = [p["state"] for p in stream.poses[20:60]]
    assert states.count("lost") >= 38, states
    assert lost["tracking_lost"] is True
    assert lost["tracking_states"]["lost"] >= 38
    assert lost["map"]["frames_integrated"] == good["map"]["frames_integrated"]
    # The pose holds the last good one while lost.
    poses = stream.matrices()
    for i in range(20, 60):
        if stream.poses[i]["state"] == "lost":
            np.testing.assert_allclose(poses[i], poses[i - 1], atol=1e-9)
    before, after = (np.asarray(c.points) for c in (cloud_before, cloud_after))
    assert len(after) == len(before)  # the same points (extraction may list them in any order)
    np.testing.assert_array_equal(after[np.lexsort(after.T)], before[np.lexsort(before.T)])
    # Back in the room, tracking recovers and says so.
    status = session_status(server.url, sid, token)
    assert stream.poses[-1]["state"] in ("ok", "weak") and status["tracking_lost"] is False
