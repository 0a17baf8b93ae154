"""The browser tests' helpers: Debian's chromium as Playwright drives it (its own browser
download does not work here), pages of the app with their console errors collected, and helpers
that read the drone out of screenshots and follow it in the page's state.

The fixtures that open them (chromium, open_page) are tests/browser/conftest.py's.
"""

from __future__ import annotations

import base64
import json
import math
import os
import time
from pathlib import Path

import cv2
import numpy as np

from tests.conftest import missing
from tests.support.paths import REPO

try:
    from playwright import sync_api
except ImportError:
    missing("pip install playwright (dev extras)")

ARTIFACTS = REPO / "test-artifacts" / "web"
CHROMIUM = Path(os.environ.get("DRONESIM_CHROMIUM", "/usr/bin/chromium"))
# Software WebGL (SwiftShader): headless machines have no GPU.
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
    "--ignore-gpu-blocklist",
    "--disable-dev-shm-usage",
]
PHONE = {
    "viewport": {"width": 390, "height": 844},
    "has_touch": True,
    "is_mobile": True,
    "device_scale_factor": 1,
}
DESKTOP = {"viewport": {"width": 1280, "height": 800}}
REPLAY_PATH = "/?mode=demo-small"  # the page with the small demo preselected
APP_READY = "window.dronesim && window.dronesim.protocol && window.dronesim.pilot"
READY_TEXT = "test: the app started"
# Once the module scripts ran (the load event), the app's start is window.dronesim.ready.
READY_SIGNAL = f"""addEventListener("load", () => Promise.resolve(window.dronesim?.ready)
  .then(() => console.debug({READY_TEXT!r})));"""


class Page:
    """A page of the app in its own browser context, with its console errors collected."""

    def __init__(self, browser, server, path: str = "/", init=None, **context) -> None:
        self.context = browser.new_context(**context)
        if init is not None:
            init(self.context)  # e.g. an emulated device's scripts, before the page loads
        self.context.add_init_script(script=READY_SIGNAL)
        self.page = self.context.new_page()
        self.errors: list[str] = []
        self.page.on("pageerror", lambda e: self.errors.append(f"pageerror: {e}"))
        self.page.on(
            "console", lambda m: m.type == "error" and self.errors.append(f"console: {m.text}")
        )
        # Wait for the app's start without running script in the page: Playwright runs every
        # evaluate (and wait_for_function's polls) as a user gesture, which would give the page
        # the transient activation a real page opened from a link does not have (?autostart=live
        # would then start AR with no tap). The page says it started on its console.
        with self.page.expect_console_message(lambda m: m.text == READY_TEXT, timeout=20_000):
            self.page.goto(f"{server.url}{path}")
        self.page.wait_for_function(APP_READY, timeout=20_000)

    def snapshot(self) -> dict:
        """What the page saw (``window.dronesim.snapshot()``)."""
        return self.page.evaluate("window.dronesim.snapshot()")

    def wait(self, js: str, timeout_s: float = 30.0, what: str = "") -> None:
        """Wait for a JS condition; on time-out, fail with what the page had seen."""
        try:
            self.page.wait_for_function(js, timeout=timeout_s * 1000, polling=100)
        except sync_api.TimeoutError:
            s = self.snapshot()
            keys = (
                "connection",
                "poses",
                "states",
                "sent",
                "droneStates",
                "mapPoints",
                "errors",
                "events",
                "commands",
                "mesh",
                "fpv",
            )
            brief = json.dumps({k: s.get(k) for k in keys}, default=str)[:3000]
            raise AssertionError(
                f"timed out after {timeout_s} s waiting for {what or js}; page saw {brief}"
            ) from None

    def redraw(self, change: str, view: str, what: str) -> None:
        """Run ``change`` (JS statements that change what ``view`` draws and mark it dirty) and
        wait until ``view`` (a JS expression: a view with ``lastRender``) has drawn since, and
        the page has composited it. Not a fixed wait: where the page finds the stream behind,
        its views draw up to 800 ms apart (views/render_budget.js)."""
        self.page.evaluate(f"() => {{ {change}; window.__changedAt = performance.now(); }}")
        self.wait(f"{view}.lastRender > window.__changedAt", 10, what)
        self.page.evaluate("new Promise((r) => requestAnimationFrame(() => setTimeout(r, 50)))")

    def screenshot(self, name: str, selector: str | None = None) -> np.ndarray:
        """Save a screenshot (of the page or one element) under test-artifacts/web; -> RGB."""
        ARTIFACTS.mkdir(parents=True, exist_ok=True)
        target = self.page.locator(selector) if selector else self.page
        data = target.screenshot(path=str(ARTIFACTS / name))
        bgr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)

    def close(self) -> None:
        self.context.close()


def start_replay(page: Page, min_poses: int, tap: bool = False) -> dict:
    """Press Start; wait for min_poses poses and the HUD's "tracking ok"."""
    (page.page.tap if tap else page.page.click)("#btn-stream")
    page.wait(f"window.dronesim.seen.poses >= {min_poses}", 90, f"{min_poses} poses")
    page.wait(
        "document.querySelector('[data-field=tracking]').textContent === 'tracking ok'",
        30,
        "the HUD to show tracking ok",
    )
    return page.snapshot()


# ---- the drone in pictures and in the page's state ------------------------------------------


def canvas_rgb(data_url: str, name: str) -> np.ndarray:
    """A canvas's PNG (a data URL), saved under test-artifacts/web as ``name``; -> RGB."""
    data = base64.b64decode(data_url.split(",", 1)[1])
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    (ARTIFACTS / name).write_bytes(data)
    return cv2.cvtColor(
        cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB
    )


def drone_mask(rgb: np.ndarray) -> np.ndarray:
    """Pixels of the drone's magenta paint (0xff00cc, lit or in shade)."""
    r, g, b = (rgb[..., i].astype(int) for i in range(3))
    return (r > 130) & (b > 95) & (g < 90) & (r - g > 90) & (b - g > 60)


def count_near(mask: np.ndarray, xy, radius: float) -> int:
    """True pixels of mask in the square of half-size radius around xy (x, y)."""
    h, w = mask.shape
    x, y = xy
    x0, x1 = max(0, int(x - radius)), min(w, int(x + radius) + 1)
    y0, y1 = max(0, int(y - radius)), min(h, int(y + radius) + 1)
    return int(mask[y0:y1, x0:x1].sum())


def expected_drone_screen_point(snap: dict) -> tuple[float, float, float] | None:
    """Where the drone's centre must appear, (x, y) in CSS px and its depth z in metres,
    computed here from the last drone_state (T_camera_drone, or T_world_drone through the shown
    frame's pose) and the intrinsics: the page's own projection is not trusted. None when the
    centre is not in front of the camera and well inside the picture."""
    drone, pose, ar = snap["lastDrone"], snap["lastPose"], snap["ar"]
    if drone is None or pose is None or ar["shownSeq"] is None:
        return None
    if "T_camera_drone" in drone and drone.get("camera_seq", ar["shownSeq"]) == ar["shownSeq"]:
        T_cd = np.array(drone["T_camera_drone"]).reshape(4, 4)
    else:
        T_wc = np.array(pose["T_world_camera"]).reshape(4, 4)
        T_cd = np.linalg.inv(T_wc) @ np.array(drone["T_world_drone"]).reshape(4, 4)
    x, y, z = T_cd[:3, 3]
    fx, fy, cx, cy = ar["intrinsics"]
    W, H = ar["colourSize"]
    if z < 0.25:
        return None
    u, v = fx * x / z + cx, fy * y / z + cy
    if not (30 <= u <= W - 30 and 30 <= v <= H - 30):
        return None
    st = ar["stage"]
    return (
        st["left"] + (u + 0.5) / W * st["width"],
        st["top"] + (v + 0.5) / H * st["height"],
        float(z),
    )


def drone_position(snap: dict) -> np.ndarray:
    return np.array(snap["lastDrone"]["T_world_drone"]).reshape(4, 4)[:3, 3]


def wait_for_approach(page: Page, command_id: int, timeout_s: float = 25.0) -> dict:
    """Follow the drone after a goto: the target from the first drone_state that carries the
    command's id (or the id of the goto the page sends instead when the server answers that
    the target is unreachable and offers the nearest point), and its distance to it shrinking.
    Returns the first and the closest distance, metres."""
    deadline = time.time() + timeout_s
    target, d0, d_min, ids = None, None, math.inf, {command_id}
    while time.time() < deadline:
        s = page.snapshot()
        for error in s["errors"]:
            if error.get("command_id") in ids and error["name"] != "unreachable_target":
                raise AssertionError(f"the server refused the command: {error}")
        ids |= {c["id"] for c in s["commands"] if c["name"] == "goto" and c["id"] > command_id}
        drone = s["lastDrone"]
        arrived = any(e["event"] == "arrived" and e.get("command_id") in ids for e in s["events"])
        if drone and drone.get("command_id") in ids and "target" in drone:
            target = np.array(drone["target"])
            d = float(np.linalg.norm(drone_position(s) - target))
            d0 = d if d0 is None else d0
            d_min = min(d_min, d)
        if d0 is not None and (arrived or d_min <= d0 - min(0.15, 0.5 * d0) or d_min < 0.1):
            return {"start": d0, "closest": d_min, "arrived": arrived, "target": target.tolist()}
        time.sleep(0.2)
    last = json.dumps(page.snapshot()["lastDrone"], default=str)[:600]
    raise AssertionError(
        f"the drone did not approach its target within {timeout_s} s (ids {ids},"
        f" first distance {d0}, closest {d_min}; last drone state {last})"
    )
