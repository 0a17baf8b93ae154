"""Online loop closure in live sessions (server/sessions/loop_closing.py): a real server on
loopback, a real WebSocket client replaying a sequence played forward then back; the loop back
to the start is found while the session runs, the client gets map_corrected and the rebuilt
map's preview (reset), the corrected keyframes are no further from the ground truth than the
odometry's, the drone's map is replaced and the saved room holds the corrected poses."""

from __future__ import annotations

import asyncio
import json
import time

import httpx
import numpy as np

from server import protocol as P
from server.client.connection import Connection
from server.datasets import open_dataset
from server.evaluation.metrics import ate
from server.evaluation.trajectory import Trajectory
from server.mapping.config import MappingConfig
from server.registration.config import RegistrationConfig
from tests.conftest import auth
from tests.test_loops import ForwardBack

FRAMES = 100  # forward, then back: 199 frames, 16 keyframes, a loop back to the first ones
LOOPS = RegistrationConfig().with_overrides(loops={"min_separation": 8})
# Keyframes and every 10th frame fused: the map is rebuilt from keyframes anyway, and the test
# runs on a couple of shared cores.
MAPPING = MappingConfig(fuse_every=10)


def _status(server, sid: str, token: str) -> dict:
    r = httpx.get(f"{server.url}/api/sessions/{sid}", headers=auth(token), timeout=60)
    r.raise_for_status()
    return r.json()


async def _stream(server, sid: str, token: str, ds, extra: int, until=None) -> tuple[list, list]:
    """Send every frame of ``ds`` (two in flight: the server's inbox never drops one), then up
    to ``extra`` more (its first frames again, seqs going on) until a map_corrected came, and
    wait up to 20 s for ``until(messages)``; -> every server message in order, and the poses."""
    K = ds.intrinsics
    hello = P.make_hello("loops", (K.fx, K.fy, K.cx, K.cy), (K.width, K.height))
    conn = await Connection.open(f"{server.ws_url}/ws/sessions/{sid}", token, hello, timeout=60)
    messages: list[dict] = []

    conn.start(lambda m, _latency: messages.append(m))
    try:
        for seq in range(len(ds) + extra):
            if seq >= len(ds) and (until is None or conn.corrections):
                break
            assert await conn.wait_for_room(2, 60), conn.failure
            f = ds[seq % len(ds)]
            await conn.send_frame(P.make_frame(seq, float(seq) / 15, f.colour, f.depth))
        assert await conn.drain(60)
        deadline = time.monotonic() + 20  # what the last frames started (a rebuild) comes
        while until is not None and not until(messages) and time.monotonic() < deadline:
            await asyncio.sleep(0.1)
        await conn.bye()
    finally:
        await conn.close()
    return messages, [m for m in messages if m["type"] == "pose"]


def _kinds(messages: list[dict]) -> list[str]:
    return [m["type"] + ("/reset" if m.get("reset") else "") for m in messages]


def _corrected_then_reset(messages: list[dict]) -> bool:
    kinds = _kinds(messages)
    return "map_corrected" in kinds and "map_chunk/reset" in kinds[kinds.index("map_corrected") :]


def _keyframe_ate(gt: Trajectory, poses: dict[int, np.ndarray]) -> float:
    """ATE RMSE (m) of keyframe poses by seq against the ground truth (rigidly aligned)."""
    seqs = sorted(poses)
    est = Trajectory(np.array(seqs, float), np.array([poses[s] for s in seqs]))
    ref = Trajectory(np.array(seqs, float), gt.poses[[s % len(gt) for s in seqs]])
    return ate(ref, est)["rmse"]


def test_a_live_loop_corrects_the_world_map_drone_and_room(live_server, shared_data, tmp_path):
    ds = ForwardBack(open_dataset(shared_data / "synthetic_room0"), FRAMES)
    server = live_server(tmp_path / "data", registration=LOOPS, mapping=MAPPING)
    sid, token = server.create_session()
    messages, poses = asyncio.run(_stream(server, sid, token, ds, 60, _corrected_then_reset))

    kinds = _kinds(messages)
    assert "map_corrected" in kinds, "no loop closed live"
    first = kinds.index("map_corrected")
    assert "map_chunk/reset" in kinds[first:], "no rebuilt preview after map_corrected"
    corrected = [m for m in messages if m["type"] == "map_corrected"]
    latest = corrected[-1]
    assert latest["loops"] >= 1 and len(latest["keyframes"]) >= 10
    T_correction, keyframes = P.decode_map_corrected(latest)
    # Poses before from_seq are as sent (never rewritten); the keyframes' odometry is the pose
    # sent for their frame.
    sent = {p["seq"]: P.pose_matrix(p) for p in poses}
    assert corrected[0]["from_seq"] <= max(sent) + 1
    odometry = {seq: sent[seq] for seq, _ in keyframes.values()}
    fixed = {seq: T for seq, T in keyframes.values()}
    before, after = _keyframe_ate(ds.ground_truth, odometry), _keyframe_ate(ds.ground_truth, fixed)
    print(f"keyframe ATE: odometry {before * 1e3:.2f} mm, corrected {after * 1e3:.2f} mm")
    assert after <= before, (before, after)
    assert not np.allclose(T_correction, np.eye(4), atol=1e-6)  # the loop moved the world

    status = _status(server, sid, token)
    loops = status["loops"]
    print("status loops:", loops)
    assert loops["enabled"] and loops["found"] >= 1 and loops["corrections"] >= 1
    assert loops["rebuilds"] >= 1 and loops["last_rebuild_ms"] > 0
    assert loops["keyframes"] >= len(keyframes) and loops["last_optimise_ms"] < 1000
    assert status["failures"]["loops_failed"] == 0
    deadline = time.monotonic() + 10  # the flight thread applies the rebuilt map at its step
    while status["drone"]["corrections"] < 1 and time.monotonic() < deadline:
        time.sleep(0.2)
        status = _status(server, sid, token)
    assert status["drone"]["spawned"] and status["drone"]["corrections"] >= 1

    server.stop()  # shutdown saves every session: its room takes the corrected poses
    meta = json.loads((tmp_path / "data" / "sessions" / sid / "room" / "room.json").read_text())
    room = {
        k["frame_index"]: np.array(k["T_world_keyframe"]).reshape(4, 4) for k in meta["keyframes"]
    }
    assert set(fixed) <= set(room)
    assert _keyframe_ate(ds.ground_truth, room) <= before
    assert max(np.abs(room[s] - odometry[s]).max() for s in fixed) > 1e-3  # not the odometry


def test_a_sequence_without_a_loop_sends_no_map_corrected(live_server, shared_data, tmp_path):
    ds = open_dataset(shared_data / "synthetic_room0")
    server = live_server(tmp_path / "data", registration=LOOPS, mapping=MAPPING)
    sid, token = server.create_session()
    messages, poses = asyncio.run(_stream(server, sid, token, _First(ds, 60), 0))
    assert len(poses) >= 50  # (two frames in flight: the server may drop one now and then)
    kinds = _kinds(messages)
    assert "map_corrected" not in kinds and "map_chunk/reset" not in kinds
    loops = _status(server, sid, token)["loops"]
    assert loops["enabled"] and loops["keyframes"] >= 3, loops
    assert loops["found"] == 0 and loops["corrections"] == 0 and loops["rebuilds"] == 0


class _First:
    """The first ``n`` frames of a sequence."""

    def __init__(self, ds, n: int) -> None:
        self.ds, self.n, self.intrinsics = ds, n, ds.intrinsics

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, i: int):
        return self.ds[i]
