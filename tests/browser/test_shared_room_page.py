"""The page in a shared room, in a real browser: a viewer link of a room's owner draws the other
phone's drone and camera and lists the room's pilots; a page invites a phone (the link and its
QR code, made in the page), a second page opens the link, joins the room (told to look at a
mapped part of the room until it is placed) and each page draws the other's drone; a join the
server refuses shows the server's reason."""

from __future__ import annotations

import cv2
import httpx
import numpy as np

from server.datasets import open_dataset
from tests.conftest import LoopThread, Stream, auth
from tests.support.browser import DESKTOP, PHONE, canvas_rgb, count_near
from tests.support.rest import drone_spawned, wait_for_status

PLACE_HINT = "Move the phone over a part of the room that is already mapped"
ROOM = "window.dronesim.snapshot().room"
# The AR view drawn now and its canvas read back at once, with the other drones' pixels.
DRAW_AR_JS = """() => {
  const ar = window.dronesim.ar;
  ar.render(0);
  const src = ar.renderer.domElement;
  const canvas = document.createElement('canvas');
  canvas.width = src.width; canvas.height = src.height;
  canvas.getContext('2d').drawImage(src, 0, 0);
  const png = canvas.toDataURL('image/png');
  return { png, others: ar.lastDraw.others, colourSize: ar.colourSize };
}"""


def _stream(server, sid: str, token: str, ds, first: int, n: int) -> None:
    """Frames ``first``.. of ``ds`` as seqs 0..n-1, each waiting for its pose (in a loop of its
    own: Playwright's sync API holds this thread's)."""

    async def run() -> None:
        s = await Stream(server.ws_url, sid, token, ds).open()
        await s.send_range(range(n), first_index=first)
        await s.close()

    with LoopThread() as loop:
        loop.run(run(), 120)


def _path(server, url: str) -> str:
    """A link the server made (http://127.0.0.1:port/...) as a path of the test's server."""
    assert url.startswith(server.url), url
    return url[len(server.url) :]


def _paint(rgb: np.ndarray, colour: int) -> np.ndarray:
    """Pixels near a drone paint's hue (lit or in shade): another pilot's drone colour."""
    want = np.array([(colour >> 16) & 255, (colour >> 8) & 255, colour & 255], float)
    hsv = cv2.cvtColor(rgb, cv2.COLOR_RGB2HSV).astype(int)
    hue = cv2.cvtColor(want.astype(np.uint8)[None, None], cv2.COLOR_RGB2HSV)[0, 0, 0]
    dh = np.minimum(abs(hsv[..., 0] - hue), 180 - abs(hsv[..., 0] - hue))
    return (dh <= 6) & (hsv[..., 1] > 150) & (hsv[..., 2] > 90)


def test_a_viewer_of_the_owner_draws_the_joined_phones_drone_and_camera(
    live_server, open_page, shared_data
):
    server = live_server()
    ds = open_dataset(shared_data / "7scenes_a")
    a, token_a = server.create_session()
    _stream(server, a, token_a, ds, 0, 40)
    wait_for_status(server.url, a, token_a, drone_spawned, "the owner's drone", 60)
    r = httpx.post(f"{server.url}/api/sessions/{a}/invites", headers=auth(token_a))
    assert r.status_code == 201, r.text
    r = httpx.post(
        f"{server.url}/api/sessions", json={"join": a}, headers=auth(r.json()["join_token"])
    )
    assert r.status_code == 201, r.text
    b, token_b = r.json()["id"], r.json()["token"]
    _stream(server, b, token_b, ds, 60, 20)
    wait_for_status(server.url, b, token_b, drone_spawned, "the joined phone's drone", 60)
    status_b = httpx.get(f"{server.url}/api/sessions/{b}", headers=auth(token_b)).json()
    drone_b = np.array(status_b["drone"]["position"])

    # A viewer link of the owner: the room's two pilots, the owner marked as the watched one.
    r = httpx.post(f"{server.url}/api/sessions/{a}/viewers", headers=auth(token_a))
    assert r.status_code == 201, r.text
    viewer = open_page(server, _path(server, r.json()["url"]), **DESKTOP)
    viewer.wait(f"{ROOM}.others_drawn === 1 && {ROOM}.map_cameras.length === 1", 30, "the room")
    s = viewer.snapshot()
    room = s["room"]
    assert room["pilots"] == ["test", "test"] and room["you"] == 0, room
    assert room["placed"] == [True, True] and "none" not in room["modes"], room
    assert len(room["listed"]) == 2 and "(watched)" in room["listed"][0], room["listed"]
    assert "(watched)" not in room["listed"][1] and room["modes"][1] in room["listed"][1]
    assert viewer.page.is_visible("#room-row") and not viewer.page.is_visible("#place-hint")

    # The other drone where the room message puts it (the joined phone's own drone state),
    # and the joined phone's camera where its last tracked pose was.
    drawn = room["map_others"][0]
    last = np.reshape(s["lastRoom"]["drones"], (2, 7))
    assert drawn["index"] == 1 and np.allclose(drawn["position"], last[1, :3], atol=1e-4)
    assert np.linalg.norm(last[1, :3] - drone_b) < 0.3, (last[1], drone_b)
    cameras = np.reshape(s["lastRoom"]["cameras"], (2, 7))
    assert np.allclose(room["map_cameras"][0]["position"], cameras[1, :3], atol=1e-4)
    own = np.array(s["lastDrone"]["T_world_drone"]).reshape(4, 4)[:3, 3]
    assert np.linalg.norm(drawn["position"] - own) > 0.01  # the other's, not the watched one
    viewer.screenshot("room-viewer.png")

    # On the map, in its colour: paint that is gone when the others are hidden.
    shown = _paint(viewer.screenshot("room-viewer-map.png", "#map-view"), 0xFF9A00).sum()
    viewer.redraw(
        "const m = window.dronesim.map; m.others.group.visible = false; m.dirty = true",
        "window.dronesim.map",
        "the map to draw",
    )
    hidden = _paint(viewer.screenshot("room-viewer-map-hidden.png", "#map-view"), 0xFF9A00).sum()
    assert shown > hidden + 20, (shown, hidden)
    assert not viewer.errors, viewer.errors


def test_a_page_invites_a_phone_that_joins_by_the_link_and_each_draws_the_others_drone(
    live_server, open_page
):
    server = live_server()
    start = "/?autostart=demo-small&fps=15"

    # A room that has mapped nothing cannot be joined: the page says the server's reason.
    c, token_c = server.create_session()
    invite = httpx.post(f"{server.url}/api/sessions/{c}/invites", headers=auth(token_c)).json()
    refused = httpx.post(
        f"{server.url}/api/sessions", json={"join": c}, headers=auth(invite["join_token"])
    )
    assert refused.status_code == 409, refused.text
    reason = refused.json()["error"]["message"]
    early = open_page(server, f"{start}#join={c}&token={invite['join_token']}", **PHONE)
    early.wait("!document.querySelector('#banner').hidden", 30, "the refusal")
    banner = early.page.text_content("#banner")
    assert "Could not join the shared room" in banner and reason in banner, banner
    assert early.snapshot()["session"] is None

    # The page's side of a room message, on hand-made ones (no room sends this page any): a
    # drone per other pilot with a mode, a camera per other placed pilot, "placing…" for a
    # phone not placed; a pilot gone or without a drone loses its drone; a room not heard of
    # for 3 s is gone.
    def room(pilots, placed, modes, drones, cameras, race=None):
        message = dict(type="room", pilots=pilots, you=0, placed=placed, modes=modes)
        message.update(drones=drones, cameras=cameras, **(race or {}))
        early.page.evaluate(
            "(m) => window.dronesim.client.dispatchEvent(new CustomEvent('room', {detail: m}))",
            message,
        )
        return early.snapshot()["room"]

    pose = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]
    moved = [0.5, -0.2, 1.5, 0.0, 0.0, 0.0, 1.0]
    seen = room(["me", "b", "c"], [True, False, True], ["hover", "none", "landed"],
                pose + [0.0] * 7 + moved, pose + [0.0] * 7 + moved)  # fmt: skip
    assert seen["others_drawn"] == 1 and seen["map_others"][0]["index"] == 2, seen
    assert np.allclose(seen["map_others"][0]["position"], moved[:3])
    assert [c["index"] for c in seen["map_cameras"]] == [2]
    assert "(you)" in seen["listed"][0] and "placing…" in seen["listed"][1], seen["listed"]
    seen = room(["me", "b"], [True, True], ["hover", "hover"], pose + moved, pose + moved)
    assert [d["index"] for d in seen["map_others"]] == [1] and len(seen["listed"]) == 2, seen
    assert seen["map_routes"] == [], seen
    # The other pilot's route ahead, drawn on the map in its colour.
    routed = dict(route_lengths=[0, 3], routes=[0.5, -0.2, 1.5, 1.0, 0.0, 1.4, 2.0, 0.5, 1.2])
    seen = room(["me", "b"], [True, True], ["hover", "goto"], pose + moved, pose + moved, routed)
    assert [r["index"] for r in seen["map_routes"]] == [1], seen
    assert np.allclose(seen["map_routes"][0]["points"], np.reshape(routed["routes"], (3, 3)))
    seen = room(["me", "b"], [True, True], ["hover", "none"], pose + [0.0] * 7, pose + moved)
    assert seen["others_drawn"] == 0 and "no drone" in seen["listed"][1], seen
    assert seen["map_routes"] == [], seen
    # A race: the countdown, then each pilot's gates, time and place, and the winner.
    race = dict(race="countdown", race_number=1, race_starts_in_s=2.4, race_gates=3)
    race.update(race_passed=[0, 0], race_missed=[0, 0], race_time_s=[0.0, 0.0])
    race.update(race_finished=[False, False], race_rank=[0, 0])
    seen = room(["me", "b"], [True, True], ["hover", "hover"], pose + moved, pose + moved, race)
    assert seen["race"] == "Race 1 starts in 3 s" and "/3" not in seen["listed"][0], seen
    race.update(race="finished", race_starts_in_s=0.0, race_passed=[3, 2], race_time_s=[6.2, 9.0])
    race.update(race_finished=[True, False], race_rank=[1, 0])
    seen = room(["me", "b"], [True, True], ["hover", "hover"], pose + moved, pose + moved, race)
    assert seen["race"] == "Race 1 won by me", seen
    assert seen["listed"][0].endswith("3/3 · 6.2 s · #1"), seen["listed"]
    assert seen["listed"][1].endswith("2/3 · 9.0 s"), seen["listed"]
    early.wait(f"{ROOM}.pilots.length === 0", 6, "the room forgotten")
    assert not early.page.is_visible("#room-row")
    early.close()

    # The owner streams the demo and invites: the link, and its QR code made in the page.
    owner = open_page(server, start, **DESKTOP)
    owner.wait("window.dronesim.seen.events.some((e) => e.event === 'spawned')", 60, "a drone")
    a = owner.snapshot()["session"]
    owner.page.click("#btn-flights")
    owner.page.click("#btn-invite")
    owner.wait(f"{ROOM}.invite !== null", 10, "the invitation")
    link = owner.snapshot()["room"]["invite"]
    assert link.startswith(f"{server.url}/#join={a}&token=")
    assert owner.page.input_value("#invite-link") == link
    qr = owner.screenshot("room-invite-qr.png", "#invite-qr")
    decoded, _, _ = cv2.QRCodeDetector().detectAndDecode(cv2.cvtColor(qr, cv2.COLOR_RGB2BGR))
    assert decoded == link
    owner.page.click("#flights button[value=close]")

    # A phone opens the link: its own session in the owner's room, told to look at a mapped
    # part of the room until placed, then drawn in each other's views.
    phone = open_page(server, start + link[len(server.url) + 1 :], **PHONE)
    phone.wait(f"{ROOM}.joined === '{a}'", 60, "the joined session")
    assert phone.page.text_content("#place-hint") == PLACE_HINT
    assert not phone.page.is_visible("#btn-invite")
    phone.wait(
        "window.dronesim.snapshot().lastPose?.state === 'ok' && !" + ROOM + ".placeHint",
        60,
        "the phone placed in the room",
    )
    s = phone.snapshot()
    assert s["room"]["placeHintShown"] and s["session"] != a
    phone.wait(f"{ROOM}.others_drawn === 1 && {ROOM}.you === 1", 60, "the owner's drone")
    owner.wait(f"{ROOM}.others_drawn === 1 && {ROOM}.you === 0", 60, "the phone's drone")

    # The owner starts a race from the page (a joined phone has no button): both pages' room
    # rows show it. A course must fit where the drone is: a random seed may not, so a few tries.
    assert not phone.page.is_visible("#btn-race")
    owner.page.click("#btn-flights")
    for _ in range(4):
        owner.page.click("#btn-race")
        owner.page.wait_for_timeout(1500)
        if owner.snapshot()["room"]["started_race"] is not None:
            break
    owner.page.click("#flights button[value=close]")
    started = owner.snapshot()["room"]["started_race"]
    assert started is not None and started["race"] >= 1 and started["gates"] == 3, started
    for page in (owner, phone):
        page.wait(f"({ROOM}.race ?? '').startsWith('Race {started['race']}')", 10, "the race")

    # The owner's drone in the phone's AR view, at the pixel its world pose projects to
    # through the shown frame's pose (computed here).
    for page in (owner, phone):
        page.page.evaluate("window.dronesim.stopStreaming('test')")
    # A loaded machine draws seldom (render_budget.js): wait for the draw of the last frame. A
    # frame still in flight when streaming stopped may bring its pose between that wait and the
    # snapshot (its frame not drawn yet): then wait for its draw too.
    for _ in range(10):
        phone.wait(
            "window.dronesim.snapshot().ar.othersSeq === window.dronesim.snapshot().lastPose?.seq",
            20,
            "the last frame drawn",
        )
        s = phone.snapshot()
        if s["ar"]["othersSeq"] == s["lastPose"]["seq"]:
            break
    drawn = s["room"]["ar_others"]
    assert len(drawn) == 1 and drawn[0]["index"] == 0, drawn
    assert s["ar"]["shownSeq"] == s["lastPose"]["seq"]
    T_cw = np.linalg.inv(np.array(s["lastPose"]["T_world_camera"]).reshape(4, 4))
    p = T_cw[:3, :3] @ np.array(drawn[0]["position"]) + T_cw[:3, 3]
    assert np.allclose(drawn[0]["cameraPoint"], p, atol=1e-3), (drawn, p)
    if p[2] > 0:
        fx, fy, cx, cy = s["ar"]["intrinsics"]
        assert np.allclose(
            drawn[0]["pixel"], [fx * p[0] / p[2] + cx, fy * p[1] / p[2] + cy], atol=0.5
        )
    else:
        assert drawn[0]["pixel"] is None
    phone.screenshot("room-phone.png")

    # In the owner's AR view the phone's drone wears its colour where the page projects it
    # (both replays start alike, so it is in the picture but for a drone flown away). Occlusion
    # off: real surfaces hide other drones too (test_shared_room_views.py), and the frame shown
    # may have one in front of it.
    owner.page.evaluate(
        "(ar => { ar.occlusion.enabled = false; ar.dirty = true })(window.dronesim.ar)"
    )
    owner.wait("window.dronesim.snapshot().occlusion.source === 'none'", 10, "a draw without it")
    # Drawn and read back in one call: the pixels the page projects are of the picture read
    # (a screenshot comes a frame or more later, with the replay's camera moved on).
    shown = owner.page.evaluate(DRAW_AR_JS)
    rgb = canvas_rgb(shown["png"], "room-owner.png")
    (drawn,) = shown["others"]
    W, H = shown["colourSize"]
    h, w = rgb.shape[:2]
    if (
        drawn["pixel"] is not None
        and 10 <= drawn["pixel"][0] <= W - 10
        and 10 <= drawn["pixel"][1] <= H - 10
    ):
        u, v = drawn["pixel"]
        xy = ((u + 0.5) / W * w, (v + 0.5) / H * h)
        assert count_near(_paint(rgb, 0xFF9A00), xy, 30 * w / W) > 15, (drawn, xy)
    assert not owner.errors and not phone.errors, owner.errors + phone.errors
