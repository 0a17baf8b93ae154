"""The load tester's encoded sequence (server/client/loadtest) keeps an iPhone recording's own pose
in every frame (the clients streaming it to a real server:
tests/server/test_iphone_stream_server.py)."""

from __future__ import annotations

import numpy as np
import pytest

from server.client.loadtest import EncodedSequence
from server.datasets import open_dataset
from tests.support.iphone_recordings import room_recording, write_r3d
from tests.support.paths import SHARED_DATA

ROOM = SHARED_DATA / "synthetic_room0"
pytestmark = pytest.mark.skipif(not ROOM.is_dir(), reason=f"shared data not found at {ROOM}")

FRAMES = 16


@pytest.fixture(scope="module")
def room():
    return room_recording(ROOM, list(range(0, 2 * FRAMES, 2)))  # every other frame: 15 fps


def test_the_encoded_sequence_keeps_each_frames_device_pose(room, tmp_path):
    ds = open_dataset(write_r3d(room, tmp_path / "scan.r3d"))
    seq = EncodedSequence.from_dataset(ds, max_frames=5)
    for i, message in enumerate(seq.frames):
        sent = np.array(message["T_device_camera"]).reshape(4, 4)
        np.testing.assert_allclose(sent, ds.device_poses.poses[i], atol=1e-12)
    # A sequence without device poses sends none, as before.
    tum = EncodedSequence.from_dataset(open_dataset(ROOM), max_frames=2)
    assert all("T_device_camera" not in m for m in tum.frames)
