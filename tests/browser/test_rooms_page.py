"""The page's "Continue in a saved room": after a session is ended, a new one opens in the room
it left (POST /api/sessions with the ended session's id and token), in a real browser."""

from __future__ import annotations

import time

import httpx

from tests.conftest import auth
from tests.support.browser import DESKTOP


def test_the_page_continues_in_the_room_of_the_session_it_ended(live_server, open_page):
    server = live_server(session_ttl_s=1.0)
    page = open_page(server, "/?autostart=demo-small&fps=30", **DESKTOP)
    page.wait("window.dronesim.seen.poses >= 20", 120, "20 poses of the first session")
    first = page.snapshot()["session"]

    # End it: the server closes it once disconnected for the TTL, and it leaves a room.
    page.page.click("#btn-menu")
    page.page.click("#btn-end")
    page.wait("localStorage.getItem('dronesim.room') !== null", 10, "the ended session kept")
    room = page.page.evaluate("JSON.parse(localStorage.getItem('dronesim.room'))")
    assert room["id"] == first
    deadline = time.time() + 60
    while not httpx.get(f"{server.url}/api/sessions/{first}", headers=auth(room["token"])).json()[
        "closed"
    ]:
        assert time.time() < deadline, "the ended session did not close"
        time.sleep(0.3)

    # Continue in its room: a new session, tracked (recognised in the room) from its frames on.
    before = page.snapshot()["poses"]
    page.page.click("#btn-menu")
    page.page.check('input[name="session"][value="room"]')
    page.page.check('input[name="mode"][value="demo-small"]')
    page.page.click("#btn-setup-start")
    page.wait(
        f"window.dronesim.snapshot().session && window.dronesim.snapshot().session !== '{first}'",
        60,
        "a new session",
    )
    page.wait(
        f"window.dronesim.seen.poses >= {before + 10} && "
        "window.dronesim.snapshot().lastPose?.state === 'ok'",
        120,
        "10 more poses, the latest tracked in the room",
    )
    s = page.snapshot()
    assert s["session"] != first
    assert not s["errors"], s["errors"]
    assert not page.errors, page.errors
