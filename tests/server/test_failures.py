"""Failures that show (server/sessions/failures.py, runtime/faults.py): each is injected, and the
test checks that it is counted (status and every pose), said on the wire, and that the session
either goes on or ends cleanly (saved, with its documented close). The worker and socket deaths of
whole servers are in test_faults.py."""

from __future__ import annotations

import asyncio
import logging
import time

import numpy as np
import pytest
import websockets

from server import protocol as P
from server.datasets import open_dataset
from server.evaluation.trajectory import read_tum
from server.geometry import Intrinsics
from server.sessions import DroneNotice, DroneUpdate, SessionError, SessionFailed
from server.sessions.errors import CommandRefused
from server.sessions.runtime.faults import inject
from server.sessions.runtime.flight import Flight
from server.sessions.runtime.fusion import FuseJob
from server.sessions.runtime.session import Session
from server.sessions.store import SessionStore
from server.sessions.updates import FrameData, PoseUpdate
from server.simulation import scenes
from server.simulation.config import SimulationConfig
from server.transport import websocket
from tests.conftest import Stream, Updates, process_running, session_status


@pytest.fixture(scope="module")
def room(shared_data):
    return open_dataset(shared_data / "synthetic_room0")


async def _answers(conn, n: int) -> list[dict]:
    """The next n poses or errors (what answers frames), skipping what comes unasked."""
    got = []
    while len(got) < n:
        msg = await conn.receive(60)
        if msg["type"] in ("pose", "error"):
            got.append(msg)
    return got


# ---- tracking and fusion fail: counted, answered, the session goes on ----------------------------


def test_a_failed_frame_and_a_failed_fusion_are_answered_and_counted_in_every_later_pose(
    live_server, room
):
    """In the worker process: the tracker raises on the 3rd frame (seq 2), the map on the first
    fusion. The client hears internal_error with seq 2; the poses after each failure, and the
    status, carry the counts; the map goes on with the other frames."""
    server = live_server()
    server.app.state.manager.faults = {"track": [3], "fuse": [1]}
    sid, token = server.create_session()
    stream = Stream(server.ws_url, sid, token, room)

    async def go():
        await stream.open()
        answers = []
        for seq in range(8):
            f = room[seq]
            await stream.conn.send(P.make_frame(seq, f.timestamp, f.colour, f.depth))
            answers += await _answers(stream.conn, 1)
        await stream.close()
        return answers

    answers = asyncio.run(go())
    error = answers[2]
    assert error["type"] == "error" and error["name"] == "internal_error", error
    assert error["seq"] == 2 and error["fatal"] is False and "injected track" in error["message"]
    poses = [a for a in answers if a["type"] == "pose"]
    assert [p["seq"] for p in poses] == [0, 1, 3, 4, 5, 6, 7]
    assert poses[0]["failures"]["frames_failed"] == 0
    assert all(p["failures"]["frames_failed"] == 1 for p in poses[2:])
    assert poses[-1]["failures"]["fusions_failed"] == 1  # fused behind the poses: by the last
    # The map fuses behind the poses, and the status shows it as of its latest fusion.
    deadline = time.monotonic() + 30
    while (status := session_status(server.url, sid, token))["map"]["frames_integrated"] < 1:
        assert time.monotonic() < deadline, "no frame fused after the failed one"
        time.sleep(0.2)
    assert status["failures"]["frames_failed"] == status["frames_failed"] == 1
    assert status["failures"]["fusions_failed"] == status["fusion_failed"] == 1
    assert status["failure"] is None
    assert set(status["failures"]) == set(poses[-1]["failures"])


# ---- the map dies: the session ends cleanly, saved -----------------------------------------------


def test_a_dead_mapping_thread_never_blocks_tracking_or_stop_and_fails_the_session(tmp_path, room):
    """The mapping thread ends on its second fusion. The client is told (SessionFailed, saved),
    frames are refused from then on, a keyframe never waits for the dead thread, and stop()
    returns at once with the trajectory and the map saved."""
    store = SessionStore(tmp_path / "data")
    session = Session("0" * 16, "hash", store)
    K = room.intrinsics
    session.configure(Intrinsics(K.fx, K.fy, K.cx, K.cy, K.width, K.height))
    inject(session, {"mapping_thread": [2]})
    updates = Updates()
    session.start(updates)
    seq = 0
    with pytest.raises(SessionError) as refused:
        for seq in range(60):  # fused every 3rd frame: the second fusion ends the thread
            f = room[seq]
            session.submit(FrameData(seq, f.timestamp, f.colour, f.depth.astype(np.float32)))
            session.drain(30)
            time.sleep(0.05)
    assert refused.value.code == "session_failed" and seq > 3
    (failed,) = updates.wait_for(SessionFailed)
    assert failed.saved and "mapping thread died" in failed.message
    assert "InjectedThreadDeath" in failed.message

    f = room[0]
    keyframe = FuseJob(99, f.colour, f.depth.astype(np.float32), np.eye(4), keyframe=True)
    t0 = time.monotonic()
    for _ in range(6):  # more than the queue holds: each would wait 10 s for a live thread
        session.fusion.queue(keyframe)
    assert time.monotonic() - t0 < 1.0

    t0 = time.monotonic()
    session.stop(save=True)
    assert time.monotonic() - t0 < 10.0
    processed = len(updates.wait_for(PoseUpdate, 1))
    meta = store.read_meta(session.id)
    assert "mapping thread died" in meta["failure"] == meta["status"]["failure"]
    assert len(read_tum(store.file(session.id, "trajectory.tum"))) == processed
    assert store.file(session.id, "map.npz").is_file()  # the map itself was alive: saved


def test_a_killed_mapping_process_ends_the_session_saved_with_every_pose(tmp_path, room):
    """In the worker process: the mapper is killed mid-session. The worker lives on to stop and
    save the session (its whole trajectory; the map as its last snapshot left it), the client
    is told (SessionFailed, saved), and nothing blocks."""
    import os

    from server.sessions.web.manager import SessionManager

    manager = SessionManager(SessionStore(tmp_path / "data"))
    try:
        session, _ = manager.create()
        updates = Updates()
        session.start(updates)
        K = room.intrinsics
        hello = P.make_hello("t", (K.fx, K.fy, K.cx, K.cy), (K.width, K.height))
        session.configure(P.decode(P.encode(hello)))
        for seq in range(4):
            f = room[seq]
            session.submit(P.encode(P.make_frame(seq, f.timestamp, f.colour, f.depth)))
            assert session.drain(30)
        worker = session.status()["worker"]
        os.kill(worker["mapper_pid"], 9)
        t0 = time.monotonic()
        for seq in range(4, 60):  # the next fusion finds the mapper gone
            try:
                f = room[seq]
                session.submit(P.encode(P.make_frame(seq, f.timestamp, f.colour, f.depth)))
                session.drain(30)
            except SessionError:
                break
        (failed,) = updates.wait_for(SessionFailed)
        assert failed.saved and "mapping process died" in failed.message
        assert time.monotonic() - t0 < 30  # no 10 s wait per keyframe
        deadline = time.monotonic() + 60
        while manager.live_count and time.monotonic() < deadline:
            time.sleep(0.1)
        assert manager.live_count == 0
        meta = manager._saved[session.id]
        poses = updates.wait_for(PoseUpdate, 1)
        assert meta["closed"] is True and "mapping process died" in meta["failure"]
        assert meta["status"]["frames_processed"] == len(poses)
        assert not process_running(worker["pid"])
        saved = read_tum(manager.store.file(session.id, "trajectory.tum"))
        assert len(saved) == len(poses)  # every pose the client got, not the last snapshot's
    finally:
        manager.shutdown()


# ---- the drone's simulation fails ----------------------------------------------------------------


def _flying(published: list, log: logging.Logger) -> Flight:
    K = Intrinsics(500.0, 500.0, 319.5, 239.5, 640, 480)
    flight = Flight(SimulationConfig(), K, None, published.append, state_hz=50.0, log=log)
    scene = scenes.room_with_door()
    fm = scene.flight_map
    observed = np.ones(fm.shape, dtype=bool)
    flight.map_changed(fm.origin, fm.blocked & observed, observed)
    T = np.eye(4)
    T[:3, :3] = flight.R_flight_world.T @ np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]])
    T[:3, 3] = flight.R_flight_world.T @ (scene.start - [0.8, 0.0, 0.0])
    flight.camera_moved(0, T, np.full((480, 640), 3.0, np.float32))
    flight._tick(0.02)
    assert flight.spawned
    return flight


def _wait(condition, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline
        time.sleep(0.01)


def test_a_failing_flight_step_is_counted_logged_once_and_faults_the_drone(caplog):
    """A few failing steps are counted and flown through; half a second of them stops the
    drone for good: one traceback in the log (not 20 a second), faulted in the status and on
    the wire (drone_event and drone_state), commands refused."""
    published: list = []
    log = logging.getLogger("test.flight")
    flight = _flying(published, log)
    tick = flight._tick
    failing = {"on": False, "calls": 0}

    def step(dt):
        if failing["on"]:
            failing["calls"] += 1
            raise FloatingPointError("a bad step")
        return tick(dt)

    flight._tick = step
    caplog.set_level(logging.ERROR, logger="test.flight")
    flight.start()
    try:
        _wait(lambda: sum(isinstance(p, DroneUpdate) for p in published) >= 3)
        failing["on"] = True  # two failing steps, then it works again
        _wait(lambda: failing["calls"] >= 2)
        failing["on"] = False
        n = len(published)
        _wait(lambda: len(published) > n + 3)
        transient = failing["calls"]
        assert flight.errors == transient < 10 and flight.fault is None
        assert flight.summary()["mode"] != "faulted" and flight.summary()["errors"] == transient

        failing["on"] = True  # for good
        _wait(lambda: flight.fault is not None)
    finally:
        flight.stop()
    assert flight.errors == failing["calls"] >= transient + 10
    assert "FloatingPointError" in flight.fault
    tracebacks = [r for r in caplog.records if r.exc_info]
    assert len(tracebacks) == 1 and "a flight step failed" in tracebacks[0].getMessage()
    assert len(caplog.records) <= 3  # the traceback, the stop, at most one rate-limited line
    notice, final = published[-2:]
    assert isinstance(notice, DroneNotice) and notice.event == "faulted"
    assert "stopped" in notice.message and "FloatingPointError" in notice.message
    assert isinstance(final, DroneUpdate) and final.mode == "faulted"
    assert not np.any(final.velocity)
    event = P.make_drone_event(notice.event, notice.timestamp, notice.position, notice.message)
    for message in (websocket._drone_state(final), event):
        P.decode(P.encode(message))  # both as the spec allows
    summary = flight.summary()
    assert summary["mode"] == "faulted" and summary["fault"] == flight.fault
    with pytest.raises(CommandRefused, match="stopped"):
        flight.command("hold", 3)


# ---- the socket's sender dies --------------------------------------------------------------------


def test_a_dying_sender_ends_the_socket_with_send_failed_and_the_client_comes_back(
    live_server, room, monkeypatch
):
    """Sending a pose raises RuntimeError (what used to end the sender unobserved): the client
    gets send_failed and close 4011 at once, the status counts it, and a reconnect goes on
    with the same session."""
    server = live_server()
    sid, token = server.create_session()
    stream = Stream(server.ws_url, sid, token, room)
    pose = websocket._pose

    def breaks_on_seq_2(item):
        if item.seq == 2:
            raise RuntimeError("a bug while sending")
        return pose(item)

    monkeypatch.setattr(websocket, "_pose", breaks_on_seq_2)

    async def go():
        await stream.open()
        await stream.send_range(range(2))
        f = room[2]
        await stream.conn.send(P.make_frame(2, f.timestamp, f.colour, f.depth))
        told = []
        with pytest.raises(websockets.ConnectionClosed) as closed:
            while True:
                msg = await stream.conn.receive(30)
                if msg["type"] in ("pose", "error"):
                    told.append(msg)
        await stream.open()  # the same token: the session goes on
        await stream.send_range(range(3, 6))
        return told, closed.value.rcvd.code

    told, code = asyncio.run(go())
    assert [(m["type"], m.get("name")) for m in told] == [("error", "send_failed")]
    assert told[0]["fatal"] is True and code == P.CLOSE_CODES["send_failed"] == 4011
    assert [p["seq"] for p in stream.poses] == [0, 1, 3, 4, 5]
    assert stream.poses[-1]["failures"]["sends_failed"] == 1
    assert stream.poses[0]["failures"]["sends_failed"] == 0
    status = session_status(server.url, sid, token)
    assert status["failures"]["sends_failed"] == 1 and status["frames_processed"] == 6
