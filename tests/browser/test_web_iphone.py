"""An iPhone user's path through the page: pick a Record3D recording in the setup dialog, the page
uploads it, the server converts it, and the page replays it with the phone's own pose in every
frame (real chromium, real server on loopback)."""

from __future__ import annotations

import httpx
import pytest

from tests.conftest import auth
from tests.support.browser import DESKTOP
from tests.support.iphone_recordings import room_recording, write_r3d
from tests.support.paths import SHARED_DATA

ROOM = SHARED_DATA / "synthetic_room0"
pytestmark = pytest.mark.skipif(not ROOM.is_dir(), reason=f"shared data not found at {ROOM}")


FRAMES = 24


def test_an_uploaded_record3d_recording_replays_with_the_phones_poses(
    live_server, open_page, tmp_path
):
    r3d = write_r3d(
        room_recording(ROOM, list(range(0, 2 * FRAMES, 2))), tmp_path / "living_room.r3d"
    )
    server = live_server()
    page = open_page(server, **DESKTOP)
    page.page.click("#btn-menu")
    page.page.set_input_files("#recording-input", r3d)
    assert page.page.is_checked('input[name="mode"][value="iphone"]')
    page.page.click("#btn-setup-start")
    page.wait("window.dronesim.seen.poses >= 12", 60, "12 poses from the uploaded recording")
    page.page.evaluate("window.dronesim.streamer.stop()")
    s = page.snapshot()
    assert "living_room: 24 frames, 24 with the phone's pose" in s["recordingStatus"]
    assert s["hello"]["colour_size"] == [640, 480] and s["hello"]["depth_scale"] == 1000
    assert s["hello"]["client_name"].endswith("living_room")
    assert s["hello"]["gravity"] is not None  # from ARKit's y-up world
    # Every frame went out with the phone's pose, and the server's tracker started from it.
    assert s["counts"]["withDevicePose"] == s["counts"]["sent"] >= 12
    assert not s["errors"], s["errors"]
    assert s["states"].get("lost", 0) == 0, s["states"]
    session = page.page.evaluate("window.dronesim.client.session")
    status = httpx.get(
        f"{server.url}/api/sessions/{session['id']}", headers=auth(session["token"])
    ).json()
    use = status["device_pose"]
    assert use["frames"] == status["frames_processed"] >= 12
    assert use["guesses"] >= use["frames"] - 1
    page.screenshot("desktop-iphone-recording.png")
    assert not page.errors, page.errors
