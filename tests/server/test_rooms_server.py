"""Rooms over the real server: a closed session leaves a room; a new session opened in it with
the room's token relocalises its first frames there, tracks in the room's frame, starts from the
room's map (the drone's too), and leaves an extended room when it closes."""

from __future__ import annotations

import asyncio
import time

import httpx
import numpy as np

from server.datasets import open_dataset
from server.geometry import invert
from server.pipeline import ground_truth_pose_at
from tests.conftest import Stream, auth
from tests.support.rest import map_caught_up, wait_for_status


def _wait_closed(server, sid: str, token: str, timeout_s: float = 60.0) -> dict:
    deadline = time.time() + timeout_s
    while time.time() < deadline:
        status = httpx.get(f"{server.url}/api/sessions/{sid}", headers=auth(token)).json()
        if status.get("closed"):
            return status
        time.sleep(0.3)
    raise AssertionError(f"session {sid} did not close in {timeout_s} s")


def _stream(server, sid: str, token: str, ds, first: int, n: int, then=None) -> Stream:
    """Frames ``first``.. of ``ds`` as seqs 0..n-1, each waiting for its pose; then
    ``then()`` (in a thread) while the socket is still open: a connected session is never
    closed for its TTL."""

    async def run() -> Stream:
        s = await Stream(server.ws_url, sid, token, ds).open()
        await s.send_range(range(n), first_index=first)
        if then is not None:
            await asyncio.to_thread(then)
        await s.close()
        return s

    return asyncio.run(run())


def test_a_session_opened_in_a_saved_room_relocalises_and_tracks_in_its_frame(
    live_server, shared_data, tmp_path
):
    server = live_server(tmp_path / "data", session_ttl_s=1.0)
    ds = open_dataset(shared_data / "7scenes_a")

    # 1. The first visit maps frames 0-39 and closes (disconnected for the TTL): a room.
    a, token_a = server.create_session()
    _stream(server, a, token_a, ds, 0, 40)
    closed = _wait_closed(server, a, token_a)
    assert closed["map"]["frames_integrated"] > 0

    # 2. Opening the room needs its token: none is 401, another's is 404 (as an unknown id).
    url = f"{server.url}/api/sessions"
    assert httpx.post(url, json={"room": a}).status_code == 401
    other, other_token = server.create_session()
    r = httpx.post(url, json={"room": a}, headers=auth(other_token))
    assert r.status_code == 404 and r.json()["error"]["code"] == "not_found"
    r = httpx.post(url, json={"room": other}, headers=auth(other_token))  # live: no room yet
    assert r.status_code == 409 and r.json()["error"]["code"] == "room_unavailable"
    r = httpx.post(url, json={"room": a}, headers=auth(token_a))
    assert r.status_code == 201, r.text
    created = r.json()
    assert created["room"] == a and created["token"] != token_a
    b, token_b = created["id"], created["token"]

    # 4 (below) reads b's map while b is live: after its frames, the mapper (behind the poses)
    # and the drone's map (behind the mapper) catch up while the socket stays open, since a
    # disconnected session is closed after the TTL (1 s here), its drone stopped.
    live: dict = {}

    def caught_up() -> None:
        live["status"] = wait_for_status(server.url, b, token_b, map_caught_up, "b's map")
        live["drone"] = wait_for_status(
            server.url,
            b,
            token_b,
            lambda st: (st["drone"] or {}).get("map_frames", 0) >= 1,
            "b's drone map",
        )["drone"]

    # 3. The return visit starts 20 frames later: found in the room within a few frames, and
    # its poses are those of the room's frame (session a's first camera), not its own origin.
    s = _stream(server, b, token_b, ds, 60, 20, then=caught_up)
    states = [p["state"] for p in s.poses]
    first_ok = next(k for k, st in enumerate(states) if st != "lost")
    assert first_ok <= 5 and states.count("lost") == first_ok, states
    T_room_gt = invert(ground_truth_pose_at(ds, ds[0].timestamp))  # a's first camera = origin
    poses = s.matrices()
    for k in range(first_ok, 20):
        T_true = T_room_gt @ ground_truth_pose_at(ds, ds[60 + k].timestamp)
        assert np.linalg.norm(poses[k][:3, 3] - T_true[:3, 3]) < 0.05, (k, poses[k], T_true)

    # 4. Its map started as the room's: it holds a's fused frames and its own; the drone's map
    # was fed from it.
    status = live["status"]
    assert status["map"]["frames_integrated"] > closed["map"]["frames_integrated"], status
    assert live["drone"]["map_frames"] >= 1
    assert status["failures"]["room_keyframes_failed"] == 0

    # 5. Closed, it leaves the room extended: a third session may open it with b's token.
    _wait_closed(server, b, token_b)
    r = httpx.post(url, json={"room": b}, headers=auth(token_b))
    assert r.status_code == 201, r.text
