"""The page as a second phone: the owner shares a viewer link, a second browser opens it and
watches the map and the drone live with its controls off; the owner replays a recorded flight
over the map and races its ghost."""

from __future__ import annotations

import time

import numpy as np

from tests.support.browser import DESKTOP, PHONE, REPLAY_PATH, drone_mask, start_replay

SPAWNED = "window.dronesim.seen.events.some((e) => e.event === 'spawned')"


def _position(state: dict) -> np.ndarray:
    return np.array(state["T_world_drone"]).reshape(4, 4)[:3, 3]


def test_a_viewer_link_watches_the_drone_move_and_the_owner_replays_the_flight(
    live_server, open_page
):
    server = live_server()
    owner = open_page(server, REPLAY_PATH, **DESKTOP)
    start_replay(owner, 25)
    owner.wait(SPAWNED, 40, "the drone to spawn")

    # The owner shares a viewer link; a phone opens it beside the owner's page.
    owner.page.click("#btn-flights")
    owner.page.click("#btn-share")
    owner.wait("window.dronesim.snapshot().viewerLink !== null", 10, "a viewer link")
    url = owner.snapshot()["viewerLink"]
    assert "#watch=" in url and owner.page.input_value("#viewer-link") == url
    owner.page.click("#flights button[value=close]")
    viewer = open_page(server, url.split("127.0.0.1:" + str(server.port))[1], **PHONE)
    viewer.wait(
        "window.dronesim.seen.droneStates > 5 && window.dronesim.seen.mapPoints > 1000",
        30,
        "the watched map and drone",
    )
    s = viewer.snapshot()
    assert s["viewer"] and s["connection"] == "open"
    assert all(viewer.page.is_disabled(b) for b in ("#btn-takeoff", "#btn-land", "#btn-stream"))
    assert viewer.page.evaluate("document.body.classList.contains('layout-map')")
    before = _position(s["lastDrone"])

    # The owner lands the drone: the viewer sees it go down, live.
    owner.page.click("#btn-land")
    viewer.wait("window.dronesim.seen.events.some((e) => e.event === 'landed')", 30, "the landing")
    time.sleep(0.5)
    s = viewer.snapshot()
    moved = np.linalg.norm(_position(s["lastDrone"]) - before)
    assert moved > 0.2, f"the viewer saw the drone move {moved:.2f} m"
    assert s["sent"] == 0 and s["commands"] == []  # a viewer sends nothing
    owner_snap = owner.snapshot()
    assert not [e for e in owner_snap["errors"] if e["name"] == "read_only"]
    owner.screenshot("viewer-owner.png")
    rgb = viewer.screenshot("viewer-watching.png", "#map-view")
    assert drone_mask(rgb).sum() > 15, "no drone paint in the viewer's map view"

    # The landing closed the first flight: the owner replays it over the map.
    owner.page.click("#btn-flights")
    owner.wait("document.querySelectorAll('#flight-list li').length >= 1", 10, "the flight list")
    owner.page.click("#flight-list li[data-flight='1'] button:text('Replay')")
    owner.wait("window.dronesim.snapshot().replay.playing", 5, "the replay to start")
    first = owner.snapshot()["replay"]
    # The replay's clock moves on the page's animation frames, which a loaded machine spaces out
    # (0.49 s of replay in 1.5 s once): wait for it to move rather than for a fixed time.
    owner.wait(
        f"window.dronesim.snapshot().replay.elapsed > {first['elapsed']} + 0.5", 15, "the replay"
    )
    later = owner.snapshot()["replay"]
    assert first["flight"] == "1" and later["elapsed"] > first["elapsed"] + 0.5
    assert later["pose"] is not None
    owner.screenshot("viewer-owner-replay.png")

    # The ghost of the best (the only) flight, for the next attempt.
    owner.page.click("#btn-flights")
    owner.page.check("#ghost-best")
    owner.wait("window.dronesim.snapshot().ghost.flight === '1'", 10, "the ghost of flight 1")
    assert not owner.errors and not viewer.errors, owner.errors + viewer.errors

    # The page's flight arithmetic on a flight built here: the best flight is the best score
    # (else the longest), a pose between two rows is interpolated, the ghost's clock starts
    # when the live drone leaves the ground.
    out = owner.page.evaluate("""async () => {
      const { bestFlight, poseAt, Ghost } = await import('/app/js/views/flight_replay.js');
      const s = Math.SQRT1_2;
      const flight = { start_time_s: 10, duration_s: 1, state_columns:
          ['t', 'x', 'y', 'z', 'vx', 'vy', 'vz', 'qx', 'qy', 'qz', 'qw', 'mode'],
        states: [[10, 0, 0, 0, 0, 0, 0, 0, 0, 0, 1, 'hover'],
                 [11, 2, 0, 0, 0, 0, 0, 0, 0, s, s, 'manual']] };
      const ghost = new Ghost(window.dronesim.map);
      ghost.set(flight);
      ghost.droneState({ timestamp: 5, mode: 'landed' });
      const before = ghost.marker.pose.position;
      ghost.droneState({ timestamp: 6, mode: 'hover' });
      ghost.droneState({ timestamp: 6.5, mode: 'hover' });
      const after = ghost.marker.pose.position;
      ghost.set(null);
      return {
        scored: bestFlight([{ id: '1', duration_s: 9, result: { score: 3 } },
                            { id: '2', duration_s: 2, result: { score: 7 } }]).id,
        longest: bestFlight([{ id: '1', duration_s: 9, result: null },
                             { id: '2', duration_s: 2, result: null }]).id,
        none: bestFlight([]),
        mid: poseAt(flight, 0.5), end: poseAt(flight, 5), before, after,
      };
    }""")
    assert out["scored"] == "2" and out["longest"] == "1" and out["none"] is None
    assert np.allclose(out["mid"]["position"], [1, 0, 0])
    assert np.allclose(out["mid"]["quaternion"], [0, 0, np.sin(np.pi / 8), np.cos(np.pi / 8)])
    assert np.allclose(out["end"]["position"], [2, 0, 0]) and out["end"]["mode"] == "manual"
    assert np.allclose(out["before"], [0, 0, 0]) and np.allclose(out["after"], [1, 0, 0])
