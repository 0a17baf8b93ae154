"""A viewer's outbox (server/transport/viewer_socket.py): what a viewer that stopped reading holds
(viewer links through the real server: tests/server/test_viewers_server.py)."""

from __future__ import annotations

import asyncio

import numpy as np


def test_a_slow_viewers_queue_keeps_the_newest_state_and_drops_its_oldest_updates():
    """What a viewer that stopped reading holds: at most OUTBOX items, the newest pose and
    drone state in place of older ones, the oldest events and chunks dropped (counted)."""
    from server.registration.results import TrackingState
    from server.sessions import DroneNotice, DroneUpdate, PoseUpdate
    from server.simulation.drone_types import DroneEventKind
    from server.transport.viewer_socket import OUTBOX, viewer_outbox

    def state(t: float) -> DroneUpdate:
        return DroneUpdate(t, np.eye(4), None, None, np.zeros(3), "hover", 1.0, None, None, None)

    def pose(seq: int) -> PoseUpdate:
        return PoseUpdate(seq, seq / 15, np.eye(4), TrackingState.OK, 100, False, {}, 0, seq)

    async def run() -> list:
        outbox = viewer_outbox()
        for k in range(1000):  # 50 s of a session: states at 20 Hz, poses, two events a second
            outbox.put(state(k * 0.05))
            if k % 2 == 0:
                outbox.put(pose(k // 2))
            if k % 10 == 0:
                outbox.put(DroneNotice(DroneEventKind.REPLANNED, k * 0.05, np.zeros(3), "", None))
        assert len(outbox.items) <= OUTBOX and outbox.dropped > 0
        return [await outbox.get() for _ in range(len(outbox.items))]

    waiting = asyncio.run(run())
    states = [i for i in waiting if isinstance(i, DroneUpdate)]
    poses = [i for i in waiting if isinstance(i, PoseUpdate)]
    assert len(states) == 1 and states[0].timestamp == 999 * 0.05  # only the newest waits
    assert len(poses) == 1 and poses[0].seq == 499
    events = [i for i in waiting if isinstance(i, DroneNotice)]
    assert events[-1].timestamp == 990 * 0.05  # the newest events are kept
