"""A course on the page in a real browser (headless chromium, a real server): the demo replayed,
a course started from the Course panel with the autopilot demo, its gates drawn as rings in the
AR view and on the map (seen in screenshots: the pixels they add), the HUD's time, gates and
score, a gate passed, the run finished and in the panel's best list.

Screenshots go to the test's tmp dir and to ``test-artifacts/web/``.
"""

from __future__ import annotations

import shutil

import numpy as np

from tests.support.browser import ARTIFACTS, DESKTOP, REPLAY_PATH, start_replay
from tests.support.rest import map_caught_up, wait_for_status

COURSE = "window.dronesim.course"


def shot(page, tmp_path, name: str, selector: str | None = None) -> np.ndarray:
    """A screenshot saved in the test's tmp dir (and test-artifacts/web) -> RGB."""
    rgb = page.screenshot(name, selector)
    shutil.copy(ARTIFACTS / name, tmp_path / name)
    return rgb


def pixels_added(page, tmp_path, name: str, selector: str, group: str, hide: str = "") -> int:
    """Pixels of ``selector`` that the course's ``group`` (arGroup, mapGroup) changes: a
    screenshot with the rings, one without (scaled to nothing: the course messages keep
    setting the groups' visibility; both views redrawn in between)."""

    view = "map" if group == "mapGroup" else "ar"

    def draw(visible: bool) -> np.ndarray:
        # A fixed 150 ms once saw no change: the view had not drawn yet (Page.redraw).
        page.redraw(
            f"const c = {COURSE}; c.{group}.scale.setScalar({1 if visible else 0});"
            f" c.ar.dirty = true; c.map.dirty = true; {hide}",
            f"{COURSE}.{view}",
            f"the {view} view to draw",
        )
        return shot(
            page, tmp_path, f"{name}-{'with' if visible else 'without'}-rings.png", selector
        )

    without = draw(False)
    with_rings = draw(True)
    return int((np.abs(with_rings.astype(int) - without.astype(int)).sum(axis=2) > 60).sum())


def test_a_course_in_the_demo_is_drawn_flown_by_the_autopilot_and_scored(
    live_server, open_page, tmp_path
):
    server = live_server()
    page = open_page(server, REPLAY_PATH, **DESKTOP)
    start_replay(page, 30)
    # The whole demo walk (90 frames) maps the room; then the replay stops (it would loop) and
    # the drone's map catches up (every 3 s at most).
    page.wait("window.dronesim.seen.poses >= 90", 120, "the demo walk")
    page.page.click("#btn-stream")
    page.wait("!window.dronesim.streamer.running", 15, "the replay to stop")
    page.wait("window.dronesim.seen.lastDrone !== null", 30, "the drone")
    sid, token = page.page.evaluate(
        "[window.dronesim.client.saved.id, window.dronesim.client.saved.token]"
    )
    # The map is final (every frame fused) and the drone's map holds all of it: the two
    # courses below are laid on the same map. Equal counts alone held for a moment while
    # frames still waited for the mapper, which then changed the second course.
    wait_for_status(
        server.url,
        sid,
        token,
        lambda b: (
            map_caught_up(b) and b["drone"]["map_frames"] == b["map"]["frames_integrated"] > 0
        ),
        "the drone's map to hold every frame",
        30,
    )

    # The Course panel: easy, seed 0, the pilot to fly it (no autopilot yet); Start course.
    page.page.click("#btn-course")
    page.page.check("#course-dialog input[value=easy]")
    page.page.fill("#course-dialog input[name=seed]", "0")
    shot(page, tmp_path, "course-panel.png")
    page.page.click("#btn-course-start")
    # Laid, or refused when this run's map has no room for that seed: try the next seeds.
    refusals, seed = [], 0
    while True:
        page.wait(
            f"{COURSE}.course || window.dronesim.seen.errors.some((e) => e.name === 'bad_command')",
            30,
            "a course or a refusal",
        )
        if page.page.evaluate(f"{COURSE}.course !== null"):
            break
        refusals += page.page.evaluate("window.dronesim.seen.errors.splice(0)")
        seed += 1
        assert seed < 8, [e["message"] for e in refusals]
        page.page.evaluate(f"{COURSE}.start({{difficulty: 'easy', seed: {seed}}})")
    s = page.snapshot()["course"]
    course = s["course"]
    n = len(course["gates"]) // 7
    assert course["state"] == "running" and not course["autopilot"] and n == 3
    assert course["seed"] == seed and course["gate_states"] == ["pending"] * n
    assert len(s["arRings"]) == n and len(s["mapRings"]) == n
    np.testing.assert_allclose(
        [r["position"] for r in s["mapRings"]],
        np.reshape(course["gates"], (n, 7))[:, :3],
        atol=1e-5,
    )
    # The next gate stands out (green, with an arrow the way through), the others light blue.
    assert [r["colour"] for r in s["mapRings"]] == [0x00FF66, 0x38C8FF, 0x38C8FF]
    assert "gates 0/3" in s["hud"] and "score 0" in s["hud"] and "time" in s["hud"]

    # The rings on screen: the map (fitted to the room) and the AR overlay (the camera picture
    # hidden, so that only the overlay counts).
    page.page.evaluate("window.dronesim.map.fit()")
    on_map = pixels_added(page, tmp_path, "course-map", "#map-view", "mapGroup")
    assert on_map > 300, f"the rings add {on_map} pixels to the map view"
    in_ar = pixels_added(
        page,
        tmp_path,
        "course-ar",
        ".ar-stage",
        "arGroup",
        "document.querySelector('.ar-image').style.visibility = 'hidden';",
    )
    page.page.evaluate("document.querySelector('.ar-image').style.visibility = ''")
    projected = page.page.evaluate(f"""() => {{
      const c = {COURSE}, ar = c.ar, THREE_V = ar.camera.position.constructor;
      if (!ar.frame) return 0;
      let seen = 0;
      for (const ring of c.arGroup.children) {{
        const p = new THREE_V().setFromMatrixPosition(ring.matrix)
          .applyMatrix4(ar.frame.T_camera_world);
        const [w, h] = ar.colourSize, [fx, fy, cx, cy] = ar.intrinsics;
        const u = fx * p.x / p.z + cx, v = fy * p.y / p.z + cy;
        if (p.z > 0.2 && u > 0 && u < w && v > 0 && v < h) seen += 1;
      }}
      return seen;
    }}""")
    if projected:  # a ring's centre in the last picture's view: it is drawn there
        assert in_ar > 100, f"{projected} rings in view, but they add {in_ar} AR pixels"
    shot(page, tmp_path, "course-laid.png")

    # The same course again with the autopilot demo (the same seed from the same place).
    page.page.click("#btn-course")
    page.page.check("#course-dialog input[name=autopilot]")
    page.page.fill("#course-dialog input[name=seed]", str(seed))
    page.page.click("#btn-course-start")
    page.wait(f"{COURSE}.course.course_id === 2", 30, "the autopilot's course")
    again = page.snapshot()["course"]["course"]
    assert again["autopilot"] and again["seed"] == seed
    np.testing.assert_allclose(again["gates"], course["gates"], atol=0.05)

    # It flies through the gates: a gate passed, its ring recoloured, the HUD counts.
    page.wait(f"{COURSE}.course.gate_states.includes('passed')", 30, "a gate passed")
    s = page.snapshot()["course"]
    assert any(e["event"] == "gate_passed" for e in s["log"])
    assert 0x2F7D4A in {r["colour"] for r in s["mapRings"]}  # a passed gate's colour
    shot(page, tmp_path, "course-gate-passed.png")
    page.wait(f"{COURSE}.course.state === 'finished'", 40, "the course to finish")
    s = page.snapshot()
    course = s["course"]["course"]
    assert course["gate_states"] == ["passed"] * n and course["rank"] == 1
    assert f"gates {n}/{n}" in s["course"]["hud"]
    assert f"score {course['score']}" in s["course"]["hud"]
    assert not [e for e in s["events"] if e["event"] in ("collision", "crash")]
    shot(page, tmp_path, "course-finished.png")

    # The panel lists the run among the session's best (from the REST route).
    page.wait(f"{COURSE}.best.length >= 1", 10, "the best list")
    page.page.click("#btn-course")
    listed = page.page.inner_text("#course-best")
    assert f"{course['score']} pts" in listed and "autopilot" in listed
    shot(page, tmp_path, "course-best.png")
    page.page.click("#course-dialog button[value=cancel]")
    assert not page.errors, page.errors
