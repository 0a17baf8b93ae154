"""The flight mode switch on the phone page, in a real browser (headless chromium, phone
viewport) against a real server: switch to angle mode, push the right stick forward, and see
the drone tilt nose down in the drone_state the server sends back; centred sticks keep
streaming in angle mode; the HUD shows the mode; back to position mode. Screenshots go to
``test-artifacts/web/``."""

from __future__ import annotations

import time

from server.simulation.config import SimulationConfig
from tests.support.browser import PHONE, REPLAY_PATH, start_replay

SPAWNED = "window.dronesim.seen.events.some((e) => e.event === 'spawned')"
# Every drone_state's attitude, mode and flight mode, kept in the page from now on.
COLLECT = """() => {
  window.flown = [];
  window.dronesim.client.addEventListener("drone_state", ({ detail: s }) =>
    window.flown.push({ attitude: s.attitude, mode: s.mode, flight_mode: s.flight_mode,
      command_id: s.command_id ?? null }));
}"""


def test_angle_mode_from_the_page_tilts_the_drone(live_server, open_page):
    page = open_page(live_server(), REPLAY_PATH, **PHONE)
    start_replay(page, 20, tap=True)
    page.wait(SPAWNED, 60, "the drone to spawn")
    page.wait("window.dronesim.seen.lastDrone?.flight_mode === 'position'", 10, "a drone_state")
    assert page.page.inner_text("[data-field=flight-mode]") == "sticks position"

    # The switch sends flight_mode; the server's state confirms it; the HUD shows it.
    page.page.tap("[data-flight-mode=angle]")
    page.wait("window.dronesim.seen.lastDrone.flight_mode === 'angle'", 10, "angle mode")
    assert page.page.inner_text("[data-field=flight-mode]") == "sticks angle"
    assert page.page.get_attribute("[data-flight-mode=angle]", "aria-pressed") == "true"
    assert page.page.get_attribute("[data-flight-mode=position]", "aria-pressed") == "false"
    sent = [c for c in page.snapshot()["commands"] if c["name"] == "flight_mode"]
    assert sent and sent[-1]["fields"] == {"flight_mode": "angle"}

    # Push the right stick fully forward for 0.6 s: the drone tilts nose down (attitude pitch
    # towards angle_max_deg, 40 degrees), in manual flight.
    page.page.evaluate(COLLECT)
    stick = page.page.locator("#stick-right").bounding_box()
    cx, cy = stick["x"] + stick["width"] / 2, stick["y"] + stick["height"] / 2
    page.page.mouse.move(cx, cy)
    page.page.mouse.down()
    page.page.mouse.move(cx, cy - stick["height"] * 0.6, steps=3)
    time.sleep(0.6)
    page.screenshot("flight-mode-angle.png")
    page.page.mouse.up()
    t_release = time.time()
    time.sleep(0.8)
    flown = page.page.evaluate("window.flown")
    pitches = [s["attitude"][1] for s in flown if s["attitude"]]
    max_angle = SimulationConfig().angle_max_deg
    assert max(pitches) > 0.5 * max_angle, pitches  # tilted forward, as the server reports
    assert max(pitches) < max_angle + 4.0
    assert all(s["flight_mode"] == "angle" for s in flown)
    assert any(s["mode"] == "manual" for s in flown)

    # Released in angle mode, the sticks keep streaming (centred): fresh, as angle mode needs.
    sticks = [c for c in page.snapshot()["commands"] if c["name"] == "sticks"]
    pushed = max(i for i, c in enumerate(sticks) if c["fields"]["sticks"][2] > 0.5)
    released = sticks[pushed + 1 :]
    assert all(c["fields"]["sticks"] == [0, 0, 0, 0] for c in released)
    waited = time.time() - t_release
    assert len(released) >= 6, f"{len(released)} centred sticks in {waited:.1f} s"

    # Back to position mode: confirmed, and the streaming of centred sticks stops.
    page.page.tap("[data-flight-mode=position]")
    page.wait("window.dronesim.seen.lastDrone.flight_mode === 'position'", 10, "position mode")
    time.sleep(0.3)
    before = len(page.snapshot()["commands"])
    time.sleep(0.6)
    after = [c for c in page.snapshot()["commands"][before:] if c["name"] == "sticks"]
    assert not after, after
    assert page.page.inner_text("[data-field=flight-mode]") == "sticks position"

    # The switch stays on screen beside the sticks in landscape too (controls over the views).
    page.page.set_viewport_size({"width": 844, "height": 390})
    time.sleep(0.5)
    page.screenshot("flight-mode-landscape.png")
    for selector in ("#flight-mode", "#btn-land", "#stick-left", "#stick-right"):
        box = page.page.locator(selector).bounding_box()
        assert box and box["width"] > 20 and box["height"] > 20, selector
        assert box["x"] >= 0 and box["x"] + box["width"] <= 845, selector
        assert box["y"] >= 0 and box["y"] + box["height"] <= 391, selector
    assert not page.errors, page.errors
