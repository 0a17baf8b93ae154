"""Loop closure as the page shows it: the page replays the demo there and back (its walk, then
back to where it started) into a real server; the server recognises the start again, corrects
its keyframes and re-fuses its map; the page gets map_corrected, redraws its trail through the
corrected keyframes, starts its map afresh from the reset chunk and says so."""

from __future__ import annotations

from server.mapping.config import MappingConfig
from tests.support.browser import DESKTOP


def test_the_page_redraws_its_map_when_the_server_closes_a_loop(live_server, open_page, tmp_path):
    # The demo's corrections move its keyframes by under a millimetre, which the server's
    # defaults do not re-fuse (mapping.rebuild_min_move_m): here every correction re-fuses.
    server = live_server(tmp_path / "data", mapping=MappingConfig(rebuild_min_move_m=0.0))
    page = open_page(server, "/?autostart=demo-loop&fps=30&view=map", **DESKTOP)
    page.wait("window.dronesim.seen.corrections.length >= 1", 240, "a map_corrected message")
    # Said on the page (shown for 5 s; a second loop closed at once shows a second one).
    assert page.page.locator(".toast", has_text="loop closed").count() >= 1
    page.wait("window.dronesim.seen.mapResets >= 1", 60, "the re-fused map (a reset chunk)")
    snap = page.snapshot()
    correction = snap["corrections"][0]
    assert correction["loops"] >= 1 and correction["keyframes"] >= 10, correction
    # The way back had come past the start's keyframes when the loop was found.
    assert correction["from_seq"] > 150, correction
    # The trail went through the keyframes, then on with each later pose: fewer points than
    # poses (before the correction each pose had added one).
    assert correction["keyframes"] <= snap["trail"]["points"] < snap["poses"], snap["trail"]
    assert snap["mapPoints"] > 1000  # the rebuilt map came back
    assert not page.errors, page.errors
