"""The loop demo's index, as the page gets it (server/transport/routes_client.py): the demo
forward, then back to its first frame."""

from __future__ import annotations

import numpy as np

from server.datasets.replay_export import replay_index
from server.geometry import Intrinsics
from server.transport.routes_client import there_and_back


def test_the_loop_demo_plays_the_demo_forward_then_back_to_its_first_frame():
    frames = [{"timestamp": 10.0 + i / 30, "colour": f"c{i}", "depth": f"d{i}"} for i in range(5)]
    index = replay_index("demo", Intrinsics(525, 525, 319.5, 239.5, 640, 480), 5000.0, None, frames)
    played = there_and_back(index)["frames"]
    assert [f["colour"] for f in played] == ["c0", "c1", "c2", "c3", "c4", "c3", "c2", "c1", "c0"]
    assert [f["depth"] for f in played][-1] == "d0"
    stamps = np.array([f["timestamp"] for f in played])
    assert stamps[0] == 10.0 and np.allclose(np.diff(stamps), 1 / 30, atol=1e-5)
    assert index["frames"] == frames  # the demo's own index is left as it was
