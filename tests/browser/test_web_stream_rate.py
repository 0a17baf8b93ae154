"""The page on a weak GPU, in a real browser against a real server on loopback: drawing adapts so
that the stream keeps its rate, the HUD names what a stream behind its rate waits for from
measured times, and FPV is never an empty picture while its mesh is on the way.

(``benchmarks/page_stream.py`` measures the rate itself, at phone size and pixel ratio 2.)
"""

from __future__ import annotations

import numpy as np

from tests.support.browser import PHONE

SPAWNED = "window.dronesim.seen.events.some((e) => e.event === 'spawned')"
SKY = np.array([0x27, 0x31, 0x3F])  # fpv_view.js: where the map has no surface

# Every AR draw made to take 150 ms of the main thread, as a weak GPU's driver would.
SLOW_DRAWS = """() => {
  const ar = window.dronesim.ar, render = ar.render.bind(ar);
  ar.render = (...args) => {
    const t0 = performance.now();
    while (performance.now() - t0 < 150) {}
    return render(...args);
  };
}"""


def test_slow_draws_lower_the_pixel_ratio_and_the_hud_says_the_page_is_busy(live_server, open_page):
    phone = {**PHONE, "device_scale_factor": 2}
    page = open_page(live_server(), "/?mode=demo-small&view=ar&frameBudgetMs=20", **phone)
    before = page.snapshot()["budget"]
    # Headless chromium draws WebGL in software: the page starts at pixel ratio 1, not 2.
    assert before["software"] and before["maxRatio"] == 1 == before["pixelRatio"], before
    page.page.evaluate(SLOW_DRAWS)
    page.page.tap("#btn-stream")
    page.wait(
        "window.dronesim.snapshot().budget.pixelRatio < window.dronesim.snapshot().budget.maxRatio",
        40,
        "the pixel ratio to drop under slow draws",
    )
    page.wait(
        "window.dronesim.snapshot().waitsFor === 'page'", 40, "the HUD to name the page as the wait"
    )
    chip = page.page.locator("[data-field=held]")
    assert chip.is_visible()
    text = chip.text_content()
    assert text.startswith("page busy: draw"), text
    s = page.snapshot()
    assert s["load"]["top"] == "draw" and s["load"]["fraction"] > 0.3, s["load"]
    # The views draw at the budget's ratio, and less often while the stream is behind.
    ratio = page.page.evaluate("window.dronesim.ar.renderer.getPixelRatio()")
    assert ratio == s["budget"]["pixelRatio"], (ratio, s["budget"])
    assert s["budget"]["drawIntervalMs"] >= 100, s["budget"]
    # Behind for windows in a row, the views draw less often still (the interval doubles).
    page.wait(
        "window.dronesim.snapshot().budget.drawIntervalMs >= 200",
        30,
        "the draw interval to grow while the stream stays behind",
    )
    assert not page.errors, page.errors


# The views held to one draw every 800 ms (the budget's longest), the budget's own adapting off.
SELDOM_DRAWS = """() => {
  const budget = window.dronesim.budget;
  budget.update = () => {};
  budget.streamBehind = false;
  budget.intervalMs = 800;
}"""


def test_a_page_that_draws_seldom_reads_the_depth_only_of_frames_it_draws(live_server, open_page):
    """Poses come faster than the AR view draws (a slow page): the replay's depth PNGs, read for
    occlusion, are read only for the frame shown last before a draw, not for every frame; the
    frame left on screen gets its depth."""
    page = open_page(live_server(), "/?mode=demo-small&view=ar", **PHONE)
    page.page.evaluate(SELDOM_DRAWS)
    page.page.tap("#btn-stream")
    page.wait("window.dronesim.seen.poses >= 3", 90, "the first poses")
    before = page.snapshot()
    page.wait(f"window.dronesim.seen.poses >= {before['poses'] + 20}", 60, "20 more poses")
    page.page.evaluate("window.dronesim.streamer.stop()")
    page.wait(
        "window.dronesim.snapshot().occlusion.depthSeq === window.dronesim.ar.frame?.seq",
        10,
        "the depth of the frame left on screen",
    )
    after = page.snapshot()
    shown = after["poses"] - before["poses"]
    reads = after["occlusion"]["depthReads"] - before["occlusion"]["depthReads"]
    assert after["budget"]["drawIntervalMs"] == 800, after["budget"]
    assert 1 <= reads <= 0.5 * shown, (reads, shown)
    assert after["occlusion"]["depthFailures"] == 0
    assert not page.errors, page.errors


def test_fpv_shows_the_map_points_and_says_the_map_is_loading_before_its_mesh(
    live_server, open_page, tmp_path
):
    server = live_server()
    page = open_page(server, "/?mode=demo-small&view=fpv", **PHONE)
    page.page.route("**/mesh.ply", lambda route: route.abort())  # the mesh never comes
    page.page.tap("#btn-stream")
    page.wait(f"{SPAWNED} && window.dronesim.seen.lastDrone", 90, "the drone to spawn")
    page.wait("window.dronesim.snapshot().fpv.points > 500", 30, "FPV to draw the map's points")
    page.wait("window.dronesim.snapshot().mesh.failures >= 1", 30, "the mesh's request to fail")
    s = page.snapshot()
    assert not s["fpv"]["drawn"] and s["fpv"]["hint"] == "loading the map…", s["fpv"]
    hint = page.page.locator("#fpv-view .empty-hint")
    assert hint.is_visible() and hint.text_content() == "loading the map…"
    # The picture is not empty: the points cover part of it (everything else is sky).
    rgb = page.screenshot("fpv-points.png", ".fpv-canvas")
    drawn = np.abs(rgb.astype(int) - SKY).sum(axis=2) > 30
    assert drawn.mean() > 0.005, f"only {drawn.mean():.2%} of the FPV picture shows map points"
    assert s["mesh"]["triangles"] == 0, s["mesh"]
    errors = [e for e in page.errors if "mesh.ply" not in e and "ERR_FAILED" not in e]
    assert not errors, errors


ADAPT_INTERVAL = """async () => {
  const { RenderBudget, RENDER_BUDGET } = await import("/app/js/views/render_budget.js");
  const budget = new RenderBudget({ software: true, devicePixelRatio: 1 });
  let now = budget.windowStart;
  const windows = (n, behind) => {
    budget.streamBehind = behind;
    const seen = [];
    for (let i = 0; i < n; i++) {
      now += RENDER_BUDGET.windowMs + 1;
      budget.update(now);
      seen.push(budget.drawIntervalMs);
    }
    return seen;
  };
  return { base: budget.drawIntervalMs, behind: windows(10, true), atRate: windows(12, false),
    limits: RENDER_BUDGET };
}"""


def test_the_draw_interval_grows_while_the_stream_is_behind_and_comes_back_at_rate(
    live_server, open_page
):
    """RenderBudget's adapted interval, driven window by window with the page's own module: at
    least slowDrawMs as soon as the stream is behind, doubling every overWindows windows up to
    maxDrawMs, halving every calmWindows windows at rate back to the software base."""
    page = open_page(live_server(), "/?mode=demo-small", **PHONE)
    r = page.page.evaluate(ADAPT_INTERVAL)
    limits = r["limits"]
    assert r["base"] == limits["softwareDrawMs"]
    behind = r["behind"]
    assert behind[0] == limits["slowDrawMs"] and 2 * limits["slowDrawMs"] in behind, behind
    assert behind == sorted(behind) and behind[-1] == limits["maxDrawMs"], behind
    at_rate = r["atRate"]
    assert at_rate[0] == limits["maxDrawMs"], at_rate  # one calm window is not enough
    assert at_rate == sorted(at_rate, reverse=True) and at_rate[-1] == limits["softwareDrawMs"]
    assert not page.errors, page.errors
