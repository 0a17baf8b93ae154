"""Online loop closure in live sessions (server/sessions/runtime/loop_closing.py): a real server on
loopback, a real WebSocket client replaying a sequence played forward then back; the loop back
to the start is found while the session runs, the client gets map_corrected and the rebuilt
map's preview (reset), the corrected keyframes are no further from the ground truth than the
odometry's, the drone's map is replaced and the saved room holds the corrected poses."""

from __future__ import annotations

import asyncio
import dataclasses
import json
import time

import httpx
import numpy as np

from server import protocol as P
from server.client.connection import Connection
from server.datasets import open_dataset
from server.datasets.there_and_back import ThereAndBack
from server.evaluation.metrics import ate
from server.evaluation.trajectory import Trajectory
from server.mapping.config import MappingConfig
from server.registration.config import RegistrationConfig
from tests.conftest import auth
from tests.support.rest import wait_for_status

FRAMES = 100  # forward, then back: 199 frames, 16 keyframes, a loop back to the first ones
LOOPS = RegistrationConfig().with_overrides(loops={"live": True, "min_separation": 8})
# Keyframes and every 10th frame fused: the map is rebuilt from keyframes anyway, and the test
# runs on a couple of shared cores.
MAPPING = MappingConfig(fuse_every=10)
# The synthetic room's corrections move keyframes by under a millimetre, which the defaults
# leave unfused (mapping.rebuild_min_move_m): to test the rebuild, every correction re-fuses.
REFUSE_ALL = dataclasses.replace(MAPPING, rebuild_min_move_m=0.0)


def _status(server, sid: str, token: str) -> dict:
    r = httpx.get(f"{server.url}/api/sessions/{sid}", headers=auth(token), timeout=60)
    r.raise_for_status()
    return r.json()


def _settled(status: dict) -> bool:
    """The session's loops are settled: every correction so far was rebuilt into the map (its
    reset preview sent), skipped or failed (a rebuild runs behind the frames, on the mapping
    thread, seconds behind on a busy machine)."""
    loops = status["loops"]
    return loops["corrections"] >= 1 and not loops["rebuild_pending"]


async def _stream(
    server, sid: str, token: str, ds, extra: int, settled=None, until=None
) -> tuple[list, list]:
    """Send every frame of ``ds`` (two in flight: the server's inbox never drops one), then up
    to ``extra`` more (its first frames again, seqs going on) until a map_corrected came; then,
    still connected, wait until the status says ``settled(status)``, and for
    ``until(messages)`` (what the server sent before its status said so);
    -> every server message in order, and the poses."""
    K = ds.intrinsics
    hello = P.make_hello("loops", (K.fx, K.fy, K.cx, K.cy), (K.width, K.height))
    conn = await Connection.open(f"{server.ws_url}/ws/sessions/{sid}", token, hello, timeout=60)
    messages: list[dict] = []

    conn.start(lambda m, _latency: messages.append(m))
    try:
        for seq in range(len(ds) + extra):
            if seq >= len(ds) and conn.corrections:
                break
            assert await conn.wait_for_room(2, 60), conn.failure
            f = ds[seq % len(ds)]
            await conn.send_frame(P.make_frame(seq, float(seq) / 15, f.colour, f.depth))
        assert await conn.drain(60)
        if settled is not None:
            await asyncio.to_thread(
                wait_for_status, server.url, sid, token, settled, "the session's loops"
            )
        deadline = time.monotonic() + 30  # sent already: on its way through the web process
        while until is not None and not until(messages):
            assert time.monotonic() < deadline, _kinds(messages)
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
    ds = ThereAndBack(open_dataset(shared_data / "synthetic_room0"), FRAMES)
    server = live_server(tmp_path / "data", registration=LOOPS, mapping=REFUSE_ALL)
    sid, token = server.create_session()
    messages, poses = asyncio.run(
        _stream(server, sid, token, ds, 60, _settled, _corrected_then_reset)
    )

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
    # The synthetic room's odometry is off by under 3 mm over these keyframes, and a correction
    # moves them by fractions of a millimetre: "no further" holds within 5 % (live runs gave
    # 2-10 % closer, once 2 % further; the offline test tests/unit/registration/test_loops.py
    # 6-11 % closer).
    assert after <= 1.05 * before, (before, after)
    assert not np.allclose(T_correction, np.eye(4), atol=1e-6)  # the loop moved the world

    status = _status(server, sid, token)
    loops = status["loops"]
    print("status loops:", loops)
    assert loops["enabled"] and loops["found"] >= 1 and loops["corrections"] >= 1
    assert loops["rebuilds"] >= 1 and loops["last_rebuild_ms"] > 0
    assert loops["rebuilds_cpu_ms"] >= loops["last_rebuild_cpu_ms"] > 0
    assert loops["keyframes"] >= len(keyframes) and loops["last_optimise_ms"] < 1000
    assert status["failures"]["loops_failed"] == 0
    worker = status["worker"]  # the loop closer ran in a process of its own, off the tracker's
    assert worker["loops_pid"] not in (None, worker["pid"], worker["mapper_pid"])
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
    assert _keyframe_ate(ds.ground_truth, room) <= 1.05 * before
    assert max(np.abs(room[s] - odometry[s]).max() for s in fixed) > 1e-3  # not the odometry
    # The final snapshot (the room's map.npz is a link to it) came after the last rebuild.
    final = json.loads((tmp_path / "data" / "sessions" / sid / "meta.json").read_text())
    assert final["status"]["loops"]["rebuilds"] >= loops["rebuilds"] >= 1
    saved_map = tmp_path / "data" / "sessions" / sid / "room" / "map.npz"
    assert saved_map.samefile(tmp_path / "data" / "sessions" / sid / "map.npz")


def test_a_correction_below_the_maps_resolution_moves_poses_and_room_but_not_the_map(
    live_server, shared_data, tmp_path
):
    """With the defaults a sub-millimetre correction (the synthetic room's) is sent and taken
    by the tracker, the drone and the room's keyframes, but the map is not re-fused: no reset
    preview, the skip counted, how far the map is behind said (under one voxel)."""
    ds = ThereAndBack(open_dataset(shared_data / "synthetic_room0"), FRAMES)
    server = live_server(tmp_path / "data", registration=LOOPS, mapping=MAPPING)
    sid, token = server.create_session()

    messages, poses = asyncio.run(_stream(server, sid, token, ds, 60, _settled))
    kinds = _kinds(messages)
    assert "map_corrected" in kinds and "map_chunk/reset" not in kinds, "no loop, or re-fused"
    status = _status(server, sid, token)
    loops = status["loops"]
    print("status loops:", loops)
    assert loops["corrections"] >= 1 and loops["rebuilds"] == 0 and loops["rebuilds_skipped"] >= 1
    assert 0 < loops["map_behind_m"] <= MAPPING.rebuild_min_move_m
    assert loops["rebuilds_cpu_ms"] == 0
    assert status["drone"]["spawned"] and status["failures"]["loops_failed"] == 0

    server.stop()  # shutdown saves the session: its room takes the corrected poses all the same
    _, keyframes = P.decode_map_corrected([m for m in messages if m["type"] == "map_corrected"][-1])
    sent = {p["seq"]: P.pose_matrix(p) for p in poses}
    meta = json.loads((tmp_path / "data" / "sessions" / sid / "room" / "room.json").read_text())
    room = {
        k["frame_index"]: np.array(k["T_world_keyframe"]).reshape(4, 4) for k in meta["keyframes"]
    }
    # The room's poses are corrected ones (a loop found while the session stopped may have
    # moved them a little more since the last map_corrected), not the odometry sent.
    moved = max(np.abs(room[s] - sent[s]).max() for s, _ in keyframes.values())
    print(f"the room's keyframes moved by up to {moved * 1e3:.2f} mm")
    assert moved > 2e-4  # runs here: 1.3-1.4 mm
    assert (tmp_path / "data" / "sessions" / sid / "room" / "map.npz").exists()


def test_a_sequence_without_a_loop_sends_no_map_corrected(live_server, shared_data, tmp_path):
    """Also: off by default; a session turns it on, or off where the server has it on."""
    ds = open_dataset(shared_data / "synthetic_room0")
    url = f"{live_server(tmp_path / 'on', registration=LOOPS).url}/api/sessions"
    assert httpx.post(url).json()["loop_closure"] is True  # the server's setting: on
    assert httpx.post(url, json={"loop_closure": False}).json()["loop_closure"] is False
    server = live_server(tmp_path / "data", mapping=MAPPING)
    url = f"{server.url}/api/sessions"
    assert httpx.post(url).json()["loop_closure"] is False  # the server's default: off
    created = httpx.post(url, json={"loop_closure": True}).json()
    assert created["loop_closure"] is True
    sid, token = created["id"], created["token"]

    def looked_up(status: dict) -> bool:  # the loop thread (below the map's priority) caught up
        loops = status["loops"]
        return loops["keyframes"] >= 3 and loops["queued"] == 0

    messages, poses = asyncio.run(_stream(server, sid, token, _First(ds, 60), 0, looked_up))
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


# ---- the parts, one by one ------------------------------------------------------------------


def _turn(yaw_rad: float, t) -> np.ndarray:
    """4x4: a turn about z by ``yaw_rad``, then a shift by ``t`` (metres)."""
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    T[:3, 3] = t
    return T


def test_a_corrected_tracker_tracks_on_in_the_corrected_world(shared_data):
    """Tracker.apply_correction between two frames: the keyframes the graph knows take their
    corrected poses, the rest and the last pose move by the correction, and the next frames come
    out exactly as the uncorrected tracker's, moved by the correction."""
    import copy

    from server.registration import Tracker

    ds = open_dataset(shared_data / "synthetic_room0")
    a = Tracker(ds.intrinsics)
    for i in range(24):
        a.track(ds[i].colour, ds[i].depth)
        a.update_keyframe()
    b = copy.deepcopy(a)
    held = {kf.id: kf for kf in [a.keyframe, *a.recent]}
    assert len(held) >= 2
    oldest, newest = min(held), max(held)
    delta = _turn(np.radians(4.0), [0.2, -0.1, 0.05])
    known = {i: delta @ held[i].T_world_keyframe for i in held if i != newest}
    b.apply_correction(known, delta)
    b_held = {kf.id: kf for kf in [b.keyframe, *b.recent]}
    assert np.allclose(b_held[oldest].T_world_keyframe, known[oldest])
    assert np.allclose(b_held[newest].T_world_keyframe, delta @ held[newest].T_world_keyframe)
    assert np.allclose(b.T_world_last, delta @ a.T_world_last)
    assert np.allclose(b.velocity, a.velocity)  # a motion in the camera's frame: unchanged
    for i in range(24, 36):
        ra, rb = a.track(ds[i].colour, ds[i].depth), b.track(ds[i].colour, ds[i].depth)
        a.update_keyframe(), b.update_keyframe()
        assert ra.state == rb.state and ra.keyframe_id == rb.keyframe_id
        assert np.allclose(rb.T_world_camera, delta @ ra.T_world_camera, atol=1e-6), i


def test_a_rebuild_replaces_the_map_with_the_keyframes_at_their_corrected_poses(
    shared_data, tmp_path
):
    """Mapper: fused at drifted poses, rebuilt from the keyframe files at corrected ones (a
    frame fused during the rebuild goes into both), swapped in at once with a fresh preview."""
    from server.mapping.tsdf import MapError
    from server.rooms.room import room_keyframe, write_keyframe
    from server.sessions.processes.mapper import Mapper

    ds = open_dataset(shared_data / "synthetic_room0")
    K, gt = ds.intrinsics, ds.ground_truth
    drift = _turn(0.0, [0.5, 0.0, 0.0])
    frames = [0, 8, 16]
    mapper = Mapper(MappingConfig())
    for i in frames:
        f = ds[i]
        write_keyframe(tmp_path, room_keyframe(i, i, gt.poses[i], f.colour, f.depth, K, LOOPS))
        mapper.fuse(f.colour, f.depth, K, drift @ gt.poses[i])
    old_points = _occupied(mapper.map)
    with np.testing.assert_raises(MapError):
        mapper.rebuild_step()  # none started

    mapper.rebuild_start(tmp_path, [(i, gt.poses[i]) for i in frames], K)
    assert mapper.rebuild_step(1) == 2
    f = ds[24]  # fused meanwhile: the old map at its drifted pose, the new one at the true one
    mapper.fuse(f.colour, f.depth, K, drift @ gt.poses[24], rebuild_pose=gt.poses[24])
    assert mapper.map.stats()["frames_integrated"] == 4  # the old map serves until the swap
    rebuilt = mapper.rebuild_finish((0.1, np.eye(3)))
    assert rebuilt.keyframes == 3 and rebuilt.stats["frames_integrated"] == 4
    assert mapper.map.stats()["frames_integrated"] == 4 and mapper.map is not None
    # The rebuilt map is the one fused at the true poses; the old one was half a metre off.
    reference = Mapper(MappingConfig())
    for i in [*frames, 24]:
        reference.fuse(ds[i].colour, ds[i].depth, K, gt.poses[i])
    truth = _occupied(reference.map)
    new_match, old_match = _overlap(_occupied(mapper.map), truth), _overlap(old_points, truth)
    assert new_match > 0.95 and old_match < 0.85, (new_match, old_match)  # 1.0, 0.76
    assert len(rebuilt.points) == rebuilt.total_points > 1000
    assert rebuilt.occupancy is not None and rebuilt.occupancy[1].any()
    with np.testing.assert_raises(MapError):
        mapper.rebuild_finish()  # it is over


def _occupied(tsdf, cell_m: float = 0.05) -> np.ndarray:
    """Centres (N, 3) of the map's occupied cells, world metres."""
    origin, occupied, _ = tsdf.occupancy(cell_m)
    return origin + (np.argwhere(occupied) + 0.5) * cell_m


def _overlap(points: np.ndarray, truth: np.ndarray, cell_m: float = 0.05) -> float:
    """Share of ``points`` within one cell of a point of ``truth``."""
    from scipy.spatial import cKDTree

    d, _ = cKDTree(truth).query(points)
    return float(np.mean(d <= cell_m * 1.01))


def _room_drone():
    from server.simulation.config import SimulationConfig
    from server.simulation.drone import DroneSimulator
    from server.simulation.flight_map import FlightMap

    config = SimulationConfig()
    lo, hi = np.array([-0.1, -0.1, -0.1]), np.array([6.1, 4.1, 2.5])
    walls = [
        ((-0.1, -0.1, -0.1), (6.1, 4.1, 0.0)),
        ((-0.1, -0.1, 2.4), (6.1, 4.1, 2.5)),
        ((-0.1, -0.1, 0.0), (0.0, 4.1, 2.4)),
        ((6.0, -0.1, 0.0), (6.1, 4.1, 2.4)),
        ((0.0, -0.1, 0.0), (6.0, 0.0, 2.4)),
        ((0.0, 4.0, 0.0), (6.0, 4.1, 2.4)),
    ]

    def grid(t=(0.0, 0.0, 0.0)):
        t = np.asarray(t)
        moved = [(np.add(a, t), np.add(b, t)) for a, b in walls]
        m = FlightMap.from_boxes(lo + t, hi + t, moved, config.voxel_m)
        return m.origin, m.blocked, np.ones(m.shape, bool)

    drone = DroneSimulator(config, FlightMap.from_boxes(lo, hi, walls, config.voxel_m))
    drone.spawn(np.array([1.0, 2.0, 1.2]), yaw_rad=0.3)
    return drone, grid


def test_the_drone_moves_with_a_corrected_world_and_replans_its_goto():
    from server.simulation.drone_types import DroneEventKind, DroneMode

    drone, grid = _room_drone()
    drone.advance(0.5)
    before = drone.status()
    delta = _turn(0.1, [0.3, -0.2, 0.05])
    # The hovering drone moves with its world: position, heading and the point it holds.
    drone.move_with_world(delta, *grid(delta[:3, 3]))
    after = drone.status()
    p = delta[:3, :3] @ before.T_flight_drone[:3, 3] + delta[:3, 3]
    assert np.allclose(after.T_flight_drone[:3, 3], p, atol=1e-9)
    yaw = lambda T: np.arctan2(T[1, 0], T[0, 0])  # noqa: E731
    assert abs(yaw(after.T_flight_drone) - yaw(before.T_flight_drone) - 0.1) < 1e-6
    drone.advance(1.0)
    assert np.linalg.norm(drone.status().T_flight_drone[:3, 3] - p) < 0.02  # holds it there
    assert after.mode == DroneMode.HOVER

    # A goto in flight: re-planned on the new map to the moved target, and flown there.
    goal = np.array([4.5, 2.0, 1.2])
    drone.command_goto(goal)
    drone.advance(0.5)
    delta2 = _turn(-0.05, [-0.2, 0.1, 0.0])
    drone.move_with_world(delta2, *grid(delta[:3, 3] + delta2[:3, 3]))
    events = drone.advance(0.0)
    moved_goal = delta2[:3, :3] @ goal + delta2[:3, 3]
    assert DroneEventKind.REPLANNED in [e.kind for e in events]
    assert np.allclose(drone.status().target, moved_goal)
    for _ in range(200):
        events += drone.advance(0.1)
        if DroneEventKind.ARRIVED in [e.kind for e in events]:
            break
    assert DroneEventKind.ARRIVED in [e.kind for e in events]
    assert np.linalg.norm(drone.status().T_flight_drone[:3, 3] - moved_goal) < 0.15


def test_a_course_route_in_flight_is_not_followed_into_a_corrected_world():
    """A route planned elsewhere (a course's autopilot, through gates laid in the old world):
    the drone holds where the correction put it, and says so (blocked)."""
    from server.simulation.drone_types import DroneEventKind, DroneMode
    from server.simulation.route_following import plan_route

    drone, grid = _room_drone()
    start = drone.status().T_flight_drone[:3, 3]
    route = plan_route(drone.flight_map, start, np.array([4.5, 3.0, 1.2]), drone.config, 1.0)

    def replan(at):
        return plan_route(drone.flight_map, at, np.array([4.5, 3.0, 1.2]), drone.config, 1.0)

    drone.command_route(route, replan)
    drone.advance(0.5)
    assert drone.status().mode == DroneMode.GOTO
    drone.move_with_world(_turn(0.0, [0.1, 0.0, 0.0]), *grid((0.1, 0.0, 0.0)))
    events = drone.advance(0.0)
    assert DroneEventKind.BLOCKED in [e.kind for e in events]
    assert drone.status().mode == DroneMode.HOVER and drone.status().target is None


def test_a_viewers_map_backlog_restarts_at_a_rebuilt_maps_preview():
    from server.sessions.updates import MapCorrected, MapUpdate
    from server.sessions.web.viewers import Viewers, ViewerSocket

    viewers = Viewers()
    got: list = []
    viewers.listen(ViewerSocket("v", got.append, lambda code, message: None))
    pts, rgb = np.zeros((10, 3), np.float32), np.zeros((10, 3), np.uint8)
    for seq in range(3):
        viewers.deliver(MapUpdate(seq, pts, rgb, 10 * (seq + 1)))
    corrected = MapCorrected(1, 3, np.eye(4), [(0, 0, np.eye(4))], 0)
    viewers.deliver(corrected)
    viewers.deliver(MapUpdate(3, pts[:4], rgb[:4], 4, reset=True))
    viewers.deliver(MapUpdate(4, pts, rgb, 14))
    assert corrected in got  # a viewer is told of the correction as the owner is
    backlog = viewers.listen(ViewerSocket("w", lambda item: None, lambda code, message: None))
    maps = [u for u in backlog if isinstance(u, MapUpdate)]
    assert [u.seq for u in maps] == [3, 4] and viewers.map_points == 14


def test_a_failing_loop_keyframe_and_rebuild_are_counted_and_the_session_goes_on(
    shared_data, tmp_path
):
    """The loop closer raises on the 2nd keyframe and the map's rebuild on its first step: each
    is counted in loops_failed (status and the poses after it), the keyframe is left out of the
    graph, the old map stays, and frames go on being tracked and fused."""
    from server.config import Config
    from server.geometry import Intrinsics
    from server.sessions.config import SessionConfig
    from server.sessions.runtime.faults import inject
    from server.sessions.runtime.loop_closing import Correction
    from server.sessions.runtime.session import Session
    from server.sessions.store import SessionStore
    from server.sessions.updates import FrameData, MapCorrected, MapUpdate, PoseUpdate
    from tests.conftest import Updates

    ds = open_dataset(shared_data / "synthetic_room0")
    K = ds.intrinsics
    # The correction below moves the keyframes by 1 mm: re-fused with rebuild_min_move_m 0.
    config = SessionConfig.from_config(Config(registration=LOOPS, mapping=REFUSE_ALL))
    session = Session("1" * 16, "hash", SessionStore(tmp_path / "data"), config)
    session.configure(Intrinsics(K.fx, K.fy, K.cx, K.cy, K.width, K.height))
    assert session.loops is not None
    inject(session, {"loop_keyframe": [2], "rebuild": [1]})
    updates = Updates()
    session.start(updates)

    def send(seqs) -> None:
        for seq in seqs:
            f = ds[seq]
            session.submit(FrameData(seq, f.timestamp, f.colour, f.depth.astype(np.float32)))
            assert session.drain(30)

    send(range(40))
    deadline = time.monotonic() + 30
    while session.loop_figures()["keyframes"] < 2 and time.monotonic() < deadline:
        time.sleep(0.1)
    status = session.status()
    assert status["failures"]["loops_failed"] == 1 and status["loops"]["keyframes"] >= 2
    assert 1 not in session.loops.closer._index  # left out of the graph (its id is 1)

    # A correction moving every keyframe by 1 mm, whose rebuild fails: counted; the old map
    # stays. (A correction that moves nothing is no rebuild: the map is right as it is.)
    poses = {i: T @ _turn(0.0, (0.001, 0, 0)) for i, T in session.loops.poses().items()}
    correction = Correction(1, poses, {i: 0 for i in poses}, np.eye(4), 1, 0, 1.0)
    session.loops.worlds.add(correction)
    frames_before = session.status()["map"]["frames_integrated"]
    session._loop_corrected(correction)
    updates.wait_for(MapCorrected)
    while session.failure_counts()["loops_failed"] < 2 and time.monotonic() < deadline:
        time.sleep(0.1)
    send(range(40, 50))
    status = session.status()
    assert status["failures"]["loops_failed"] == 2 and status["loops"]["rebuilds"] == 0
    assert status["map"]["frames_integrated"] >= frames_before and status["failure"] is None
    assert not [u for u in updates.items if isinstance(u, MapUpdate) and u.reset]
    last = updates.wait_for(PoseUpdate, 50)[-1]
    assert last.seq == 49 and last.failures["loops_failed"] == 2
    session.stop(save=False)


def test_loop_closure_runs_only_where_configured_with_rooms_kept_and_not_in_a_room(tmp_path):
    """Off by default; on with registration.loops.live, but never without the room's keyframe
    files (the rebuild reads them) nor in a session continuing in a saved room (its keyframes
    keep the room's world)."""
    from server.config import Config
    from server.sessions.config import SessionConfig
    from server.sessions.runtime.session import Session
    from server.sessions.store import SessionStore

    store = SessionStore(tmp_path / "data")

    def wanted(registration=None, room_dir=None, save_rooms=True) -> bool:
        sections = {} if registration is None else {"registration": registration}
        config = SessionConfig.from_config(Config(**sections))
        config = dataclasses.replace(config, save_room=save_rooms)
        return Session("2" * 16, "hash", store, config, room_dir=room_dir).loops_wanted

    assert not wanted()
    assert wanted(LOOPS)
    assert not wanted(LOOPS, save_rooms=False)
    assert not wanted(LOOPS, room_dir=tmp_path / "a_room")


def _views(shared_data, cfg: RegistrationConfig) -> tuple:
    """synthetic_room0 every 10th frame: (its intrinsics, {frame: (place features, cleaned
    depth, true T_world_camera)})."""
    from server.pipeline import ground_truth_pose_at
    from server.registration.place import describe_place
    from server.registration.preprocess import clean_depth, to_grey

    ds = open_dataset(shared_data / "synthetic_room0")
    K = ds.intrinsics
    frames = {}
    for i in range(0, 150, 10):
        f = ds[i]
        depth = clean_depth(f.depth, cfg.depth)
        place = describe_place(to_grey(f.colour), depth, K, cfg.place, cfg.depth)
        frames[i] = (place, depth, ground_truth_pose_at(ds, f.timestamp))
    return K, frames


def _feed(loops, frames: dict, count: int, seed: int = 7) -> None:
    """Keyframes into the loop thread ``loops`` as a live session gives them, going forward and
    back over ``frames`` (and round again) for ``count`` keyframes, one at a time: each chained
    from the previous keyframe's pose carried into the latest world (the graph's own estimate
    once a correction named it), with an odometry error (0.2 deg, 3 mm) on the true motion."""
    from server.geometry import invert, orthonormalize
    from server.sessions.runtime.loop_closing import LoopKeyframe

    views = sorted(frames)
    order = ((views + views[-2:0:-1]) * 3)[:count]
    rng = np.random.default_rng(seed)
    prev = None  # (keyframe id, its view, its pose, its world)
    for kf_id, i in enumerate(order):
        place, depth, T_true = frames[i]
        world = loops.worlds.latest
        if prev is None:
            T = T_true
        else:
            T_prev = loops.worlds.carry(prev[0], prev[2], prev[3], world)
            noise = _turn(np.radians(rng.normal(0.0, 0.2)), rng.normal(0.0, 0.003, 3))
            T = orthonormalize(T_prev @ invert(frames[prev[1]][2]) @ T_true @ noise)
        loops.submit(LoopKeyframe(kf_id, i, T, world, place, depth))
        deadline = time.monotonic() + 30
        while loops.figures()["keyframes"] <= kf_id and time.monotonic() < deadline:
            time.sleep(0.005)
        prev = (kf_id, i, T, world)


def test_corrections_stay_rigid_and_small_when_every_keyframe_is_chained_from_the_graph(
    shared_data,
):
    """The loop thread as a live session feeds it, over 64 keyframes that close a loop at
    nearly every one: each keyframe is chained, as the corrected tracker chains it, from the
    previous keyframe's pose carried into the latest world (which is the graph's own estimate
    once a correction named it). Every correction stays a rotation plus a shift, and small.
    Before the graph's estimates were projected onto SO(3), each such keyframe doubled their
    rotations' departure from it: the corrections grew from millimetres to metres within ~90
    keyframes, and live sessions lost tracking for good."""
    from server.geometry import rotation_angle_deg
    from server.sessions.runtime.loop_closing import LoopClosing

    cfg = RegistrationConfig().with_overrides(loops={"live": True, "min_separation": 4})
    K, frames = _views(shared_data, cfg)
    corrections, failures = [], []
    loops = LoopClosing(K, cfg, corrections.append, failures.append)
    loops.start()
    try:
        _feed(loops, frames, 64)
    finally:
        loops.stop()
    assert not failures
    assert len(corrections) >= 30, len(corrections)
    for c in corrections:
        for T in (c.T_correction, *c.keyframes.values()):
            R = T[:3, :3]
            assert np.abs(R @ R.T - np.eye(3)).max() < 1e-12, c.world
        assert np.linalg.norm(c.T_correction[:3, 3]) < 0.1, c.world
        assert rotation_angle_deg(c.T_correction) < 3.0, c.world


def _loop_process():
    """A loop process (server/sessions/processes/loop_process.py) from the workers' forkserver, as a
    worker process's session has one: (the process, this end of its pipe)."""
    from server.sessions.processes.loop_process import loops_main
    from server.sessions.processes.session_process import _context

    ctx = _context()
    here, there = ctx.Pipe(duplex=True)
    process = ctx.Process(target=loops_main, args=(there,), daemon=True, name="test-loops")
    process.start()
    there.close()
    return process, here


def test_the_loop_process_closes_the_same_loops_as_the_loop_thread(shared_data):
    """The loop closer in a process of its own (a live session in a worker process has it
    there, off the tracker's GIL) gives the corrections it gives in the loop thread, counts
    the process's CPU, and the process ends when the session's loop thread stops."""
    from server.sessions.runtime.loop_closing import LoopClosing

    cfg = RegistrationConfig().with_overrides(loops={"live": True, "min_separation": 4})
    K, frames = _views(shared_data, cfg)
    process, conn = _loop_process()
    runs = {}
    for where in ("thread", "process"):
        corrections, failures = [], []
        loops = LoopClosing(
            K, cfg, corrections.append, failures.append, conn=conn if where == "process" else None
        )
        loops.start()
        try:
            _feed(loops, frames, 24)
            figures = loops.figures()
        finally:
            loops.stop()
        assert not failures, (where, failures)
        runs[where] = (corrections, figures)
    process.join(10)
    assert process.exitcode == 0  # ended when the loop thread let go of its pipe

    (here, here_figures), (there, there_figures) = runs["thread"], runs["process"]
    assert len(here) >= 5 and len(there) == len(here)
    assert there_figures["found"] == here_figures["found"] >= 5
    for a, b in zip(here, there, strict=True):
        assert (a.world, a.loops, a.refused) == (b.world, b.loops, b.refused)
        assert a.keyframes.keys() == b.keyframes.keys()
        for kf_id, T in a.keyframes.items():
            assert np.allclose(T, b.keyframes[kf_id], atol=1e-6), (a.world, kf_id)
        assert np.allclose(a.T_correction, b.T_correction, atol=1e-6)
    # The process's CPU is counted (the thread itself only waits on the pipe there).
    assert there_figures["lookup_cpu_ms"] > 0.3 * here_figures["lookup_cpu_ms"] > 0


def test_a_lost_loop_process_fails_each_keyframe_after_it_counted_and_the_thread_goes_on(
    shared_data,
):
    """The loop process is killed mid-session: every keyframe after it fails with a clear
    error (the session counts them as loops_failed), none blocks, and the thread stops."""
    import os
    import signal

    from server.sessions.processes.loop_process import LoopProcessError
    from server.sessions.runtime.loop_closing import LoopClosing, LoopKeyframe

    cfg = RegistrationConfig().with_overrides(loops={"live": True, "min_separation": 4})
    K, frames = _views(shared_data, cfg)
    process, conn = _loop_process()
    corrections, failures = [], []
    loops = LoopClosing(K, cfg, corrections.append, failures.append, conn=conn)
    loops.start()
    try:
        _feed(loops, frames, 3)
        assert loops.figures()["keyframes"] == 3 and not failures
        os.kill(process.pid, signal.SIGKILL)
        process.join(10)
        t0 = time.monotonic()
        place, depth, T = frames[0]
        for kf_id in (3, 4):
            loops.submit(LoopKeyframe(kf_id, 0, T, loops.worlds.latest, place, depth))
        deadline = time.monotonic() + 10
        while len(failures) < 2 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert time.monotonic() - t0 < 5
    finally:
        loops.stop(timeout_s=10)
    assert len(failures) == 2 and all(isinstance(e, LoopProcessError) for e in failures)
    assert "loop process is gone" in str(failures[0])
    assert loops.figures()["keyframes"] == 3  # the failed keyframes are not in the graph


def test_a_loop_process_gone_before_the_first_keyframe_fails_that_keyframe_not_the_hello(
    shared_data,
):
    """The loop closer is made at the session's hello: it neither waits for its process nor
    fails with it; the first keyframe then fails, counted, and the thread goes on."""
    import os
    import signal

    from server.sessions.processes.loop_process import LoopProcessError
    from server.sessions.runtime.loop_closing import LoopClosing, LoopKeyframe

    cfg = RegistrationConfig().with_overrides(loops={"live": True})
    K, frames = _views(shared_data, cfg)
    process, conn = _loop_process()
    os.kill(process.pid, signal.SIGKILL)
    process.join(10)
    failures: list = []
    loops = LoopClosing(K, cfg, lambda c: None, failures.append, conn=conn)  # no error here
    loops.start()
    place, depth, T = frames[0]
    loops.submit(LoopKeyframe(0, 0, T, 0, place, depth))
    loops.stop(timeout_s=10)
    assert len(failures) == 1 and isinstance(failures[0], LoopProcessError)
    assert loops.figures()["keyframes"] == 0
