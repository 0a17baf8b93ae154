"""Sessions in worker processes (server/sessions/processes/session_process.py,
runtime/host.py, web/live.py, web/manager.py): what crosses the pipe, errors as their own types,
thread pools shared among sessions, and a frame the tracker fails on answered, not lost. The
end-to-end paths (crash, takeover, SIGTERM) are in test_faults.py against real servers; failures
counted and a dead map in test_failures.py."""

from __future__ import annotations

import os

import msgpack
import numpy as np
import pytest

from server import protocol as P
from server.geometry import Intrinsics
from server.sessions import CommandRefused, FrameRefused, PoseUpdate
from server.sessions.runtime.session import Session
from server.sessions.store import SessionStore
from server.sessions.updates import FrameData
from server.sessions.web.manager import SessionManager
from tests.conftest import Updates


@pytest.fixture
def manager(tmp_path):
    manager = SessionManager(SessionStore(tmp_path / "data"))
    yield manager
    manager.shutdown()


@pytest.fixture(scope="module")
def room(shared_data):
    from server.datasets import open_dataset

    return open_dataset(shared_data / "synthetic_room0")


def hello(ds) -> dict:
    K = ds.intrinsics
    return P.decode(P.encode(P.make_hello("t", (K.fx, K.fy, K.cx, K.cy), (K.width, K.height))))


def frame_bytes(ds, seq: int) -> bytes:
    f = ds[seq]
    return P.encode(P.make_frame(seq, f.timestamp, f.colour, f.depth))


def streamed(manager, room, frames: int):
    """A started, configured session that has tracked the room's first ``frames`` frames, and
    the updates it sent."""
    session, _ = manager.create()
    updates = Updates()
    session.start(updates)
    session.configure(hello(room))
    for seq in range(frames):
        session.submit(frame_bytes(room, seq))
        assert session.drain(30)  # one at a time: the newest would win over a waiting frame
    return session, updates


def test_frames_cross_as_bytes_and_poses_come_back_from_another_process(manager, room):
    session, updates = streamed(manager, room, 3)
    poses = updates.wait_for(PoseUpdate, 3)
    assert [p.seq for p in poses] == [0, 1, 2]
    assert all(p.timings_ms["server_total"] >= p.timings_ms["track"] for p in poses)
    status = session.status()
    assert status["worker"]["kind"] == "process" and status["worker"]["pid"] != os.getpid()
    assert status["worker"]["loops_pid"] is None  # no loop process without online loops
    assert status["frames_received"] == 3 and status["frames_processed"] == 3


def test_errors_in_the_worker_are_raised_here_as_their_own_types(manager, room):
    session, _ = manager.create()
    with pytest.raises(CommandRefused) as refused:  # no hello yet: no drone
        session.command("hold", 7)
    assert refused.value.code == "bad_command"
    bad = hello(room) | {"intrinsics": [-500.0, 500.0, 320.0, 240.0]}  # past the codec
    with pytest.raises(P.ProtocolError) as absurd:
        session.configure(bad)
    assert absurd.value.code == "bad_intrinsics"


def test_the_worker_alone_validates_orders_and_counts_frames(manager, room):
    """The web process forwards a frame unread: the worker validates it, puts it in order and
    counts it. A refusal comes back as a FrameRefused with the frame's seq, as the client hears
    it (bad_sequence, invalid_field), and the session goes on."""
    session, _ = manager.create()
    updates = Updates()
    session.start(updates)
    session.configure(hello(room))
    invalid = P.decode(frame_bytes(room, 1)) | {"timestamp": "soon"}
    for data in (frame_bytes(room, 0), frame_bytes(room, 0), msgpack.packb(invalid)):
        session.submit(data)
        assert session.drain(30)
    session.submit(frame_bytes(room, 2))
    refused = updates.wait_for(FrameRefused, 2)
    assert [(r.seq, r.code, r.counted) for r in refused] == [
        (0, "bad_sequence", True),
        (1, "invalid_field", True),
    ]
    assert [p.seq for p in updates.wait_for(PoseUpdate, 2)] == [0, 2]
    assert session.status()["frames_received"] == 2  # those it took: in order and valid


def test_a_corrupt_frame_is_refused_with_its_seq_by_the_worker(manager, room):
    session, _ = manager.create()
    updates = Updates()
    session.start(updates)
    session.configure(hello(room))
    message = P.decode(frame_bytes(room, 0))
    message["colour"] = message["colour"][: len(message["colour"]) // 2]  # cut short
    session.submit(P.encode(message))
    session.submit(frame_bytes(room, 1))
    (refused,) = updates.wait_for(FrameRefused)
    assert refused.seq == 0 and refused.code == "corrupt_image"
    assert updates.wait_for(PoseUpdate)[0].seq == 1


def test_the_cores_are_shared_among_live_sessions(tmp_path, monkeypatch):
    """Automatic sizing: every session's native pools together use the machine's cores less
    one (the mappers' and the web process's), at least one thread each, rebalanced when a
    session comes or goes. Five cores, as the manager sees them: on a 2-core machine every
    share would be one thread, and a rebalance that never came would pass unseen."""
    monkeypatch.setattr(os, "cpu_count", lambda: 5)
    manager = SessionManager(SessionStore(tmp_path / "data"))
    cores = os.cpu_count() or 1
    try:
        first, _ = manager.create()
        assert first.status()["worker"]["threads"] == max(1, cores - 1)
        second, _ = manager.create()
        assert first.status()["worker"]["threads"] == max(1, (cores - 1) // 2)
        assert second.status()["worker"]["threads"] == max(1, (cores - 1) // 2)
        manager.delete(second.id)
        assert first.status()["worker"]["threads"] == max(1, cores - 1)
    finally:
        manager.shutdown()


def test_a_frame_the_tracker_fails_on_is_answered_and_counted(tmp_path, room):
    """A bug on one frame: the client hears internal_error with the seq, the status counts it,
    and the next frame gets its pose."""
    session = Session("0" * 16, "hash", SessionStore(tmp_path / "data"))
    K = room.intrinsics
    session.configure(Intrinsics(K.fx, K.fy, K.cx, K.cy, K.width, K.height))
    updates = Updates()
    session.start(updates)
    track = session.tracker.track
    calls = iter(range(100))

    def fails_once(colour, depth, **prior):
        if next(calls) == 1:
            raise FloatingPointError("a bug")
        return track(colour, depth, **prior)

    session.tracker.track = fails_once
    try:
        for seq in range(3):
            f = room[seq]
            session.submit(FrameData(seq, f.timestamp, f.colour, f.depth.astype(np.float32)))
            session.drain(30)
        (refused,) = updates.wait_for(FrameRefused)
        assert refused.seq == 1 and refused.code == "internal_error" and "a bug" in refused.message
        poses = updates.wait_for(PoseUpdate, 2)
        assert [p.seq for p in poses] == [0, 2]
        assert [p.failures["frames_failed"] for p in poses] == [0, 1]  # each pose says so
        assert session.status()["frames_failed"] == session.status()["failures"]["frames_failed"]
        assert session.status()["frames_failed"] == 1
    finally:
        session.stop(save=False)


def test_a_repeated_frame_is_held_at_the_last_pose_and_counted(manager, room):
    """A frame with the same images as the one before (a phone that sends its last depth again)
    keeps the previous pose and state, and the status counts it."""
    session, updates = streamed(manager, room, 2)
    f = room[1]
    session.submit(P.encode(P.make_frame(2, f.timestamp + 1 / 30, f.colour, f.depth)))
    assert session.drain(30)
    poses = updates.wait_for(PoseUpdate, 3)
    assert [p.seq for p in poses] == [0, 1, 2]
    np.testing.assert_array_equal(poses[2].T_world_camera, poses[1].T_world_camera)
    assert poses[2].state == poses[1].state == "ok"
    status = session.status()
    assert status["frames_repeated"] == 1 and status["frames_processed"] == 3
