"""The device check page (/check) in chromium: on an emulated phone of today's Chrome
(tests/support/webxr_device.py) it reports what the device gives (immersive-ar, depth format,
sizes and mapping, camera image size, depth against camera rates, the Layers API, the page's own
XRWebGLLayer) with no exception, records the user's upright answer, and downloads the same
report as JSON; in a browser without WebXR, or without AR, it says so at once. The phone page's
setup dialog links to it."""

from __future__ import annotations

import base64
import json

import cv2
import numpy as np
import pytest

from server.datasets import open_dataset
from tests.support.browser import PHONE
from tests.support.webxr_device import PROFILES, FileServer, install, prepare

# Chrome 147+ with depth on every 2nd camera frame, ARCore tracking throughout.
PROFILE = next(
    p for p in PROFILES.values() if p.layers_api and p.depth_every == 2 and not p.pose_lost
)
FRAMES = 150  # 5 s of recording: the check's 3 s and its set-up
DONE = "window.dronesimCheck && window.dronesimCheck.phase === 'done'"


def _open(chromium, server, init=None):
    """A phone-sized context on /check; the page's errors collected in ``page.errors``."""
    context = chromium.new_context(**PHONE, accept_downloads=True)
    if init is not None:
        init(context)
    page = context.new_page()
    page.errors = []
    page.on("pageerror", lambda e: page.errors.append(f"pageerror: {e}"))
    page.on("console", lambda m: m.type == "error" and page.errors.append(f"console: {m.text}"))
    page.goto(f"{server.url}/check")
    return context, page


def _steps(report: dict) -> dict[str, dict]:
    return {s["id"]: s for s in report["steps"]}


@pytest.fixture(scope="module")
def device(shared_data, tmp_path_factory):
    """The profile's recording (its first FRAMES frames) and the URL it is served at."""
    out = tmp_path_factory.mktemp("check-device")
    prepared = prepare(open_dataset(shared_data / "7scenes_a"), PROFILE, out, max_frames=FRAMES)
    files = FileServer(out)
    yield prepared, files.url
    files.close()


def test_check_reports_what_the_emulated_phone_gives(chromium, live_server, device):
    prepared, files_url = device
    config = prepared.config
    server = live_server()
    context, page = _open(chromium, server, lambda c: install(c, config, files_url))
    try:
        page.wait_for_function(
            "window.dronesimCheck?.phase === 'ready'", timeout=10_000, polling=100
        )
        page.click("#btn-start")  # a real tap: requestSession needs the user's activation
        page.wait_for_function(DONE, timeout=20_000, polling=100)
        report = page.evaluate("window.dronesimCheck.report")
        assert report["errors"] == [], report["errors"]
        steps = _steps(report)
        for name in ("secure-context", "webxr", "immersive-ar", "session", "base-layer"):
            assert steps[name]["status"] == "pass", steps[name]
        for name in ("tracking", "camera", "camera-read", "depth"):
            assert steps[name]["status"] == "pass", steps[name]
        assert report["support"] == {
            "secureContext": True,
            "webxr": True,
            "immersiveAr": True,
            "layersApi": True,
            "cameraPermission": "prompt",
        }

        s = report["session"]
        assert s["baseLayerIsXRWebGLLayer"] is True and s["endedEarlyMs"] is None
        assert {"depth-sensing", "camera-access", "local"} <= set(s["enabledFeatures"])
        assert (s["depthUsage"], s["depthDataFormat"]) == ("cpu-optimized", "luminance-alpha")
        d = s["depth"]
        assert [d["width"], d["height"]] == list(PROFILE.depth_size)
        assert d["rawValueToMeters"] == pytest.approx(0.001)
        assert np.allclose(
            d["normDepthBufferFromNormView"], config["normDepthBufferFromNormView"], atol=1e-5
        )
        assert 0.0 <= d["zeroFraction"] < 0.5
        # Depth with every 2nd new camera image (loose: the page may miss a camera image).
        assert d["distinctImages"] >= 5 and 0.3 <= d["perCameraImage"] <= 0.7, d
        c = s["camera"]
        assert [c["width"], c["height"]] == config["cameraSize"]
        assert c["distinctImages"] >= 20 and c["uprightImageSize"] is not None
        view = s["view"]
        assert view["framebuffer"] == config["viewSize"]
        K = prepared.K_view
        assert [view["intrinsics"][k] for k in ("fx", "fy", "cx", "cy")] == pytest.approx(
            [K.fx, K.fy, K.cx, K.cy], abs=0.02
        )
        assert s["xr"]["viewCount"] == 1 and s["xr"]["fps"] > 5
        assert steps["upright"]["status"] == "unknown"
        # The upright picture is the device's last camera image, the right way up.
        shown = page.evaluate("window.__xrDevice.state.frameIndex")
        error, flipped = _picture_error(page, prepared.camera_image(shown))
        assert error < 10 and flipped > 2 * error, (error, flipped)

        # The upright question, answered; the verdict follows.
        page.click("#btn-upright-yes")
        report = page.evaluate("window.dronesimCheck.report")
        assert report["upright"]["answer"] == "yes"
        assert _steps(report)["upright"]["status"] == "pass"
        assert _steps(report)["live-ar"]["status"] == "pass", _steps(report)["live-ar"]

        # The download is the report, and so is the page's <pre>.
        with page.expect_download() as info:
            page.click("#btn-download")
        download = info.value
        assert download.suggested_filename.startswith("dronesim-check-")
        assert download.suggested_filename.endswith(".json")
        assert json.loads(open(download.path()).read()) == report
        assert json.loads(page.text_content("#report")) == report
        assert page.errors == []
    finally:
        context.close()


def _picture_error(page, expected: np.ndarray) -> tuple[float, float]:
    """Mean absolute difference (0-255) of the page's upright picture from ``expected`` (RGB),
    and from ``expected`` upside down."""
    png = page.evaluate("document.querySelector('#upright-image').toDataURL('image/png')")
    data = np.frombuffer(base64.b64decode(png.split(",", 1)[1]), np.uint8)
    shown = cv2.imdecode(data, cv2.IMREAD_COLOR)[..., ::-1].astype(np.float32)
    h, w = shown.shape[:2]
    expected = cv2.resize(expected, (w, h), interpolation=cv2.INTER_AREA).astype(np.float32)
    return float(np.abs(shown - expected).mean()), float(np.abs(shown - expected[::-1]).mean())


NO_WEBXR = "delete Navigator.prototype.xr;"  # a browser without WebXR (Firefox, Safari)


@pytest.mark.parametrize(
    ("init", "failing", "words"),
    [
        (lambda c: c.add_init_script(script=NO_WEBXR), "webxr", "no WebXR"),
        (None, "immersive-ar", "isSessionSupported('immersive-ar') is false"),  # desktop chromium
    ],
    ids=["no-webxr", "no-immersive-ar"],
)
def test_check_says_at_once_what_the_browser_lacks(chromium, live_server, init, failing, words):
    server = live_server()
    context, page = _open(chromium, server, init)
    try:
        page.wait_for_function(
            "window.dronesimCheck && window.dronesimCheck.phase !== 'support'",
            timeout=5_000,
            polling=50,
        )
        report = page.evaluate("window.dronesimCheck.report")
        line = page.locator(f'#steps li[data-step="{failing}"]')
        assert line.get_attribute("data-status") == "fail"
        assert words in line.inner_text()
        assert _steps(report)["live-ar"]["status"] == "fail"
        assert report["errors"] == [] and page.errors == []
        # The phone page's setup dialog links here, next to Live AR (which such a browser lacks).
        assert 'id="check-link" href="/check"' in page.request.get(f"{server.url}/").text()
    finally:
        context.close()
