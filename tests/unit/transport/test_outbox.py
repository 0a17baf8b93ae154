"""A socket's outbox (server/transport/outbox.py) for a client that stopped reading: bounded,
oldest dropped first, but never a world's correction, the map's restart or the session's end."""

from __future__ import annotations

import asyncio

import numpy as np

from server.registration.results import TrackingState
from server.sessions import DroneUpdate, MapCorrected, MapUpdate, PoseUpdate, SessionFailed
from server.transport.outbox import Outbox, must_deliver


def pose(seq: int) -> PoseUpdate:
    return PoseUpdate(seq, seq / 15, np.eye(4), TrackingState.OK, 100, False, {}, 0, seq)


def chunk(seq: int, reset: bool = False, surface: bool = False) -> MapUpdate:
    return MapUpdate(
        seq, np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8), seq, reset, surface
    )


def state(t: float) -> DroneUpdate:
    return DroneUpdate(t, np.eye(4), None, None, np.zeros(3), "hover", 1.0, None, None, None)


def drain(outbox: Outbox) -> list:
    async def run() -> list:
        return [await outbox.get() for _ in range(len(outbox))]

    return asyncio.run(run())


def test_a_stalled_client_loses_old_poses_and_chunks_but_not_the_correction_or_the_reset():
    corrected = MapCorrected(1, 40, np.eye(4), [(3, 30, np.eye(4))], 0)
    outbox = Outbox(32, latest_only=(DroneUpdate,))
    for seq in range(200):  # a client that stopped reading while a loop closed at frame 40
        outbox.put(pose(seq))
        outbox.put(state(seq / 15))
        if seq == 40:
            outbox.put(corrected)
        outbox.put(chunk(seq, reset=seq == 41))
        assert len(outbox) <= 32
    assert outbox.dropped > 300
    waiting = drain(outbox)
    # The correction and the restart of the map come first, in their order, then the newest.
    assert waiting[0] is corrected
    assert isinstance(waiting[1], MapUpdate) and waiting[1].reset and waiting[1].seq == 41
    poses = [w.seq for w in waiting if isinstance(w, PoseUpdate)]
    assert poses == sorted(poses) and poses[-1] == 199
    states = [w for w in waiting if isinstance(w, DroneUpdate)]
    assert len(states) == 1 and states[0].timestamp == 199 / 15  # only the newest waited
    assert outbox.empty()


def test_updates_that_must_arrive_are_kept_past_the_bound():
    outbox = Outbox(2)
    # The news that the map has a surface (a chunk without points) is one of them.
    ends = [SessionFailed("the map is gone"), chunk(5, reset=True), chunk(6, surface=True)]
    for item in ends:
        outbox.put(item)
    assert all(must_deliver(item) for item in ends) and not must_deliver(chunk(7))
    assert len(outbox) == 3 and outbox.dropped == 0
    outbox.put(pose(8))  # full of updates that must arrive: the pose joins them
    outbox.put(pose(9))  # and is the one dropped for the next
    waiting = drain(outbox)
    assert waiting[:3] == ends and [w.seq for w in waiting[3:]] == [9]
    assert outbox.dropped == 1


def test_a_viewer_keeps_only_the_newest_pose_in_the_place_of_the_first():
    from server.transport.viewer_socket import viewer_outbox

    outbox = viewer_outbox(8)
    outbox.put(pose(1))
    outbox.put(chunk(1))
    outbox.put(pose(2))
    outbox.put(pose(3))
    waiting = drain(outbox)
    assert [type(w).__name__ for w in waiting] == ["PoseUpdate", "MapUpdate"]
    assert waiting[0].seq == 3
