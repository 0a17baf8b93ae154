"""What the server serves for the phone page: the page, its modules, the protocol and the demo, and
nothing beside them (the page in a real browser: tests/browser/test_web_client.py)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from tests.support.paths import REPO


def test_the_server_serves_the_page_its_modules_protocol_and_demo(live_server, demo_ready):
    import httpx

    server = live_server()
    with httpx.Client(base_url=server.url, timeout=60) as http:
        page = http.get("/")
        assert page.status_code == 200
        assert "importmap" in page.text and "/app/js/app.js" in page.text
        for path in (
            "/app/js/app.js",
            "/vendor/three/build/three.module.js",
            "/vendor/three/examples/jsm/controls/OrbitControls.js",
            "/vendor/@msgpack/msgpack/dist.esm/index.mjs",
            "/vendor/uqr/dist/index.mjs",
        ):
            r = http.get(path)
            assert r.status_code == 200, path
            assert r.headers["content-type"].startswith("text/javascript"), path
        protocol_json = (REPO / "shared" / "protocol.json").read_bytes()
        assert http.get("/protocol.json").content == protocol_json
        for path in (
            "/app/package.json",
            "/app/node_modules/three/package.json",
            "/app/js/../../README.md",
            "/app/js/%2e%2e/%2e%2e/README.md",
            "/vendor/three/../../package.json",
            "/vendor/left-pad/index.js",
            "/api/demo/files/../rgb.txt",
            "/api/demo/files/rgb.txt",
        ):
            assert http.get(path).status_code == 404, path

        index = http.get("/api/demo", params={"preset": "small"}).json()
        assert index["colour_size"] == [320, 240] and index["depth_scale"] == 5000.0
        assert len(index["frames"]) == 90 and index["intrinsics"] == [262.5, 262.5, 159.5, 119.5]
        assert np.linalg.norm(index["gravity"]) == pytest.approx(1.0)
        frame = index["frames"][0]
        colour, depth = http.get(frame["colour"]).content, http.get(frame["depth"]).content
        assert colour[:3] == b"\xff\xd8\xff" and depth[:8] == b"\x89PNG\r\n\x1a\n"
        assert cv2.imdecode(np.frombuffer(depth, np.uint8), cv2.IMREAD_UNCHANGED).dtype == np.uint16
        assert http.get("/api/demo", params={"preset": "huge"}).status_code == 404
