"""The phone page in a real browser: Debian's chromium, headless, driven by Playwright against a
real server on loopback (conftest's ``live_server``). (What the server serves for the page:
tests/server/test_web_client_server.py.)

* The live mode's frame packing, unit-tested inside the browser on the page's own ES modules:
  JPEG encoding, depth metres -> uint16 -> zlib (inflated here with Python's zlib), a whole frame
  message decoded by the server's codec, intrinsics from projection matrices with known values,
  gravity, depth resampling, and message validation against protocol.json compared with the
  server's validator case by case.
* Replay of the bundled demo on a phone viewport (390x844, touch): >= 30 frames streamed with at
  most max_in_flight in flight, poses and a "tracking ok" HUD, the drone found by its colour in
  a screenshot where its pose projects (and not there without the overlay, nor before it
  spawned), a tap on the picture that sends goto_pixel and brings the drone closer to its
  target, and the landscape layout.
* Replay on a desktop viewport (1280x800, mouse): the map view's points in a screenshot, a
  dropped connection that reconnects into the same session, the sticks at 10-20 Hz while held
  and zeros on release, hold, a click on the map that sends goto, and the map download.

Screenshots go to ``test-artifacts/web/``.
"""

from __future__ import annotations

import math
import time
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from server import protocol as proto
from server.client.connection import Connection
from tests.conftest import LoopThread
from tests.support import browser
from tests.support.browser import (
    DESKTOP,
    PHONE,
    REPLAY_PATH,
    count_near,
    drone_mask,
    expected_drone_screen_point,
    start_replay,
    wait_for_approach,
)

# ---- unit tests of the live mode's packing, in the browser ----------------------------------

PACKING_JS = """async () => {
  const P = await import('/app/js/capture/packing.js');
  const THREE = await import('three');
  const { Protocol } = await import('/app/js/network/protocol.js');
  const protocol = await Protocol.load('/protocol.json');
  const out = {};

  // colour: a smooth RGB pattern -> JPEG
  const W = 96, H = 72;
  const rgba = new Uint8ClampedArray(W * H * 4);
  for (let y = 0; y < H; y++) for (let x = 0; x < W; x++) {
    const i = 4 * (y * W + x);
    rgba[i] = 2.5 * x;
    rgba[i + 1] = 3.4 * y;
    rgba[i + 2] = 128 + 80 * Math.sin(x / 9) * Math.cos(y / 7);
    rgba[i + 3] = 255;
  }
  out.pattern = Array.from(rgba);
  const jpeg = await P.encodeJpeg(new ImageData(rgba, W, H), 0.92);
  out.jpeg = Array.from(jpeg);

  // depth: metres -> uint16 mm -> zlib, with invalid values among them
  const special = [0, 0.5, 1.2345, 2.0004, NaN, -1, 65.535, 65.6, Infinity, 3.9996, 0.0004, 0.0006];
  const depth = new Float32Array(W * H);
  for (let i = 0; i < depth.length; i++) depth[i] = 0.4 + 3.2 * ((i * 7919) % 1000) / 1000;
  depth.set(special);
  out.depthMetres = Array.from(depth, (v) => (Number.isFinite(v) ? v : String(v)));
  const packed = await P.packDepth(depth, { depthScale: 1000 });
  out.depthZlib = Array.from(packed.depth);
  out.depthFormat = packed.depthFormat;
  out.roundTrip = Array.from(new Uint16Array((await P.zlibDecompress(packed.depth)).buffer));

  // a whole hello and frame, as the live mode sends them (depth at half resolution)
  const half = P.resampleDepth(depth, W, H, W / 2, H / 2, null);
  const K = [80.0, 80.0, 47.5, 35.5];
  out.hello = protocol.hello({ clientName: 'web/test', intrinsics: K, colourSize: [W, H],
    depthSize: [W / 2, H / 2], depthScale: 1000, gravity: [0, 1, 0] });
  const valid = (v) => (Number.isFinite(v) && v > 0 && v < 60 ? v : 0);
  const frameDepth = await P.packDepth(half.map(valid));
  const frame = protocol.frame({ seq: 7, timestamp: 12.5, colour: jpeg, ...frameDepth });
  out.frameBytes = Array.from(protocol.encode(frame));
  out.helloBytes = Array.from(protocol.encode(out.hello));
  out.halfDepth = Array.from(half, valid);

  // intrinsics from projection matrices
  const cam = new THREE.PerspectiveCamera(60, 640 / 480, 0.1, 100);
  out.symmetric = P.intrinsicsFromProjection(cam.projectionMatrix.elements, 640, 480);
  const off = new THREE.Matrix4().makePerspective(-0.08, 0.05, 0.06, -0.045, 0.1, 100);
  out.offCentre = P.intrinsicsFromProjection(off.elements, 640, 480);
  const K2 = [500, 505, 300.25, 250.75];
  out.roundTripK = P.intrinsicsFromProjection(P.projectionFromIntrinsics(K2, 640, 480), 640, 480);
  out.scaled = P.scaleIntrinsics([525, 525, 319.5, 239.5], [640, 480], [160, 120]);
  // the AR overlay's camera draws a camera-frame point (OpenCV) where the pinhole model puts it
  const proj = new THREE.Matrix4().fromArray(P.projectionFromIntrinsics(K2, 640, 480));
  out.overlay = [[0.3, -0.2, 1.7], [-1.1, 0.7, 3.0], [0, 0, 0.5]].map(([x, y, z]) => {
    const ndc = new THREE.Vector3(x, -y, -z).applyMatrix4(proj);
    return [(ndc.x + 1) / 2 * 640 - 0.5, (1 - ndc.y) / 2 * 480 - 0.5];
  });

  // gravity from an XR view pose (GL camera in a y-up space)
  out.gravityLevel = P.gravityInCamera(new THREE.Matrix4().elements);
  out.gravityDown = P.gravityInCamera(new THREE.Matrix4().makeRotationX(-Math.PI / 2).elements);
  out.gravityRolled = P.gravityInCamera(new THREE.Matrix4().makeRotationZ(Math.PI / 2).elements);

  // depth resampling through normDepthBufferFromNormView: identity and a quarter turn
  const src = new Uint16Array([1, 2, 3, 4, 5, 6]); // 3 x 2
  out.resampleIdentity = Array.from(P.resampleDepth(src, 3, 2, 3, 2, null));
  const turn = [0, 1, 0, 0, -1, 0, 0, 0, 0, 0, 1, 0, 1, 0, 0, 1]; // (u, v) -> (1 - v, u)
  out.resampleTurned = Array.from(P.resampleDepth(src, 3, 2, 2, 3, turn));
  out.depthSizePortrait = P.depthSizeFor([480, 640], 256, 192);
  // a 20:9 portrait view with ARCore's 160x90 landscape buffer: depth at the colour's aspect
  out.depthSizePhone = P.depthSizeFor([288, 640], 160, 90);
  out.depthSizeLandscape = P.depthSizeFor([640, 288], 160, 90);
  // T_device_camera from an XR view pose: GL camera (y up, z back) -> OpenCV axes, row-major
  const pose = new THREE.Matrix4().makeRotationY(0.3).setPosition(0.5, 1.5, -2);
  out.viewPose = Array.from(pose.elements);
  out.deviceCamera = P.deviceCameraFromView(pose.elements);
  return out;
}"""


def test_live_mode_frame_packing_in_the_browser(live_server, open_page):
    page = open_page(live_server())
    out = page.page.evaluate(PACKING_JS)
    W, H = 96, 72

    # JPEG: complete, baseline, the pattern's colours
    jpeg = bytes(out["jpeg"])
    assert jpeg[:3] == b"\xff\xd8\xff" and jpeg.rstrip(b"\x00")[-2:] == b"\xff\xd9"
    assert b"\xff\xc0" in jpeg and b"\xff\xc2" not in jpeg, "not a baseline JPEG"
    decoded = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)[..., ::-1]
    pattern = np.array(out["pattern"], np.uint8).reshape(H, W, 4)[..., :3]
    assert decoded.shape == (H, W, 3)
    assert np.abs(decoded.astype(int) - pattern).mean() < 4.0

    # depth: zlib (RFC 1950) of little-endian uint16 millimetres; invalid -> 0
    stream = bytes(out["depthZlib"])
    assert out["depthFormat"] == "zlib"
    assert stream[0] & 0x0F == 8 and (stream[0] * 256 + stream[1]) % 31 == 0, "no zlib header"
    raw = zlib.decompress(stream)
    assert int.from_bytes(stream[-4:], "big") == zlib.adler32(raw)
    units = np.frombuffer(raw, "<u2")
    metres = np.array([float(v) for v in out["depthMetres"]], np.float32).astype(np.float64)
    with np.errstate(invalid="ignore"):
        expected = np.floor(metres * 1000 + 0.5)
        valid = np.isfinite(expected) & (expected > 0) & (expected <= 65535)
        expected = np.where(valid, expected, 0)
    np.testing.assert_array_equal(units, expected.astype(np.uint16))
    assert list(units[:12]) == [0, 500, 1235, 2000, 0, 0, 65535, 0, 0, 4000, 0, 1]
    np.testing.assert_array_equal(np.array(out["roundTrip"], np.uint16), units)

    # the whole frame through the server's codec: the same picture and depth come out
    hello = proto.decode(bytes(out["helloBytes"]), direction=proto.CLIENT_TO_SERVER)
    frame = proto.decode(bytes(out["frameBytes"]), direction=proto.CLIENT_TO_SERVER)
    assert hello["gravity"] == [0, 1, 0] and frame["depth_format"] == "zlib" and frame["seq"] == 7
    colour, depth = proto.decode_frame_images(frame, hello)
    assert colour.shape == (H, W, 3) and np.abs(colour.astype(int) - pattern).mean() < 4.0
    half = np.array(out["halfDepth"], np.float32).reshape(H // 2, W // 2)
    np.testing.assert_allclose(depth, half, atol=0.00051)
    assert proto.depth_intrinsics(hello) == pytest.approx((40.0, 40.0, 23.5, 17.5))

    # intrinsics from projection matrices: known values
    f = 240 / math.tan(math.radians(30))
    assert out["symmetric"] == pytest.approx([f, f, 319.5, 239.5], abs=1e-3)
    fx, fy = 0.1 * 640 / 0.13, 0.1 * 480 / 0.105
    cx, cy = 0.08 / 0.13 * 640 - 0.5, 0.06 / 0.105 * 480 - 0.5
    assert out["offCentre"] == pytest.approx([fx, fy, cx, cy], abs=1e-3)
    assert out["roundTripK"] == pytest.approx([500, 505, 300.25, 250.75], abs=1e-3)
    hello_640 = {
        "intrinsics": [525, 525, 319.5, 239.5],
        "colour_size": [640, 480],
        "depth_size": [160, 120],
    }
    assert out["scaled"] == pytest.approx(proto.depth_intrinsics(hello_640))
    points = [(0.3, -0.2, 1.7), (-1.1, 0.7, 3.0), (0, 0, 0.5)]
    for (u, v), (x, y, z) in zip(out["overlay"], points, strict=True):
        assert (u, v) == pytest.approx((500 * x / z + 300.25, 505 * y / z + 250.75), abs=1e-3)

    # gravity in the camera frame (OpenCV: y down, z forward)
    assert out["gravityLevel"] == pytest.approx([0, 1, 0], abs=1e-6)
    assert out["gravityDown"] == pytest.approx([0, 0, 1], abs=1e-6)  # looking at the floor
    assert out["gravityRolled"] == pytest.approx([-1, 0, 0], abs=1e-6)  # on its side, x up

    assert out["resampleIdentity"] == [1, 2, 3, 4, 5, 6]
    # view (u, v) -> buffer (1 - v, u): the view's top row is the buffer's right column, upwards
    assert out["resampleTurned"] == [3, 6, 2, 5, 1, 4]
    assert out["depthSizePortrait"] == [192, 256]
    # the protocol's hello check: depth and colour aspects within max_aspect_difference
    assert out["depthSizePhone"] == [72, 160] and out["depthSizeLandscape"] == [160, 72]
    for colour_size, depth_size in (([288, 640], [72, 160]), ([640, 288], [160, 72])):
        w, h = colour_size
        hello = proto.make_hello("web", (585, 585, w / 2, h / 2), colour_size, depth_size)
        proto.validate(hello, proto.CLIENT_TO_SERVER, strict=True)
    T_gl = np.array(out["viewPose"]).reshape(4, 4).T  # column-major -> matrix
    T_cv = np.array(out["deviceCamera"]).reshape(4, 4)  # row-major
    np.testing.assert_allclose(T_cv, T_gl @ np.diag([1.0, -1.0, -1.0, 1.0]), atol=1e-6)
    assert not page.errors, page.errors


def _validation_cases() -> list[tuple[dict, str | None, bool]]:
    """(message, direction, strict): good and bad messages of every kind."""
    hello = proto.make_hello(
        "web/test", (525, 525, 319.5, 239.5), (640, 480), (320, 240), 1000.0, gravity=(0, 1, 0)
    )
    frame = {
        "type": "frame",
        "seq": 3,
        "timestamp": 1.5,
        "colour": b"\xff\xd8\xff\xd9",
        "depth": b"\x78\x9c\x00\x00",
        "depth_format": "zlib",
    }
    pose = proto.make_pose(3, 1.5, np.eye(4), "ok", 120, {"total": 12.5}, 0, True)
    state = proto.make_drone_state(
        2.0,
        np.eye(4),
        (0.1, 0, 0),
        "goto",
        4,
        T_camera_drone=np.eye(4),
        camera_seq=3,
        clearance=0.8,
        target=(1, 2, 3),
        route=np.arange(12.0).reshape(4, 3),
    )
    chunk = proto.make_map_chunk(
        np.ones((2, 3), np.float32), np.ones((2, 3), np.uint8), 0, total_points=2
    )
    error = proto.make_error("bad_depth", "all zero", seq=3)
    course = proto.make_course(
        1,
        "running",
        "easy",
        7,
        np.ones((2, 7)),
        ["passed", "pending"],
        1,
        3.5,
        9.0,
        0,
        0,
        100,
        True,
    )
    C, S = proto.CLIENT_TO_SERVER, proto.SERVER_TO_CLIENT
    cases = [
        (hello, C, True),
        (frame, C, True),
        (pose, S, False),
        (state, S, False),
        (chunk, S, False),
        (error, S, False),
        (course, S, False),
        ({"type": "command", "id": 1, "name": "goto", "target": [1, 2, 3]}, C, True),
        (
            {"type": "command", "id": 2, "name": "goto_pixel", "pixel": [10.5, 20], "seq": 3},
            C,
            True,
        ),
        ({"type": "command", "id": 3, "name": "sticks", "sticks": [0, 0.5, -1, 1]}, C, True),
        ({"type": "command", "id": 4, "name": "land"}, C, True),
        ({"type": "command", "id": 4, "name": "flight_mode", "flight_mode": "acro"}, C, True),
        (
            {"type": "command", "id": 4, "name": "course_start", "difficulty": "hard", "seed": 3},
            C,
            True,
        ),
        ({"type": "command", "id": 4, "name": "course_start", "autopilot": True}, C, True),
        ({"type": "bye"}, C, True),
        # bad ones
        ({"type": "command", "id": 5, "name": "goto"}, C, True),  # bad_command: no target
        ({"type": "command", "id": 6, "name": "sticks", "sticks": [0, 0, 0, 1.5]}, C, True),
        ({"type": "command", "id": 7, "name": "fly"}, C, True),
        ({"type": "command", "id": 7, "name": "flight_mode"}, C, True),  # bad_command
        ({"type": "command", "id": 7, "name": "flight_mode", "flight_mode": "3d"}, C, True),
        ({"type": "command", "id": 8.5, "name": "hold"}, C, True),
        ({"type": "command", "id": True, "name": "hold"}, C, True),
        ({"type": "command", "id": 9, "name": "goto", "target": [1, 2, "__nan__"]}, C, True),
        ({"type": "command", "id": 10, "name": "goto", "target": [1, 2]}, C, True),
        ({"type": "command", "id": 11, "name": "hold", "colour": "red"}, C, True),  # strict: extra
        ({"type": "command", "id": 11, "name": "hold", "colour": "red"}, C, False),  # receiver
        ({**frame, "seq": -1}, C, True),
        ({**frame, "depth_format": "raw"}, C, True),
        ({**frame, "colour": "not bytes"}, C, True),
        ({k: v for k, v in frame.items() if k != "timestamp"}, C, True),
        ({**hello, "version": 2}, C, True),
        ({**hello, "intrinsics": [5000, 525, 319.5, 239.5]}, C, True),
        ({**hello, "intrinsics": [525, 525, 900, 239.5]}, C, True),
        ({**hello, "depth_size": [320, 320]}, C, True),
        ({**hello, "colour_size": [8, 6], "depth_size": [8, 6]}, C, True),
        ({**hello, "gravity": [0, 0, 0]}, C, True),
        ({**hello, "client_name": "x" * 65}, C, True),
        ({**hello, "client_name": "ü" * 64}, C, True),  # 64 characters: fine
        ({**chunk, "count": 3}, S, False),
        ({**error, "code": 201}, S, False),
        ({**state, "mode": "flying"}, S, False),
        ({**course, "gate_states": ["passed", "lost"]}, S, False),
        ({**course, "gates": [0.0] * 141}, S, False),
        ({"type": "command", "id": 4, "name": "course_start", "difficulty": "insane"}, C, True),
        ({"type": "command", "id": 4, "name": "course_start", "gates": 21}, C, True),
        ({**state, "route": [0.0] * 1539}, S, False),
        ({**pose, "timings_ms": {"total": -1}}, S, False),
        (pose, C, False),  # a server message from a client: unknown_type
        ({"type": "teleport"}, None, False),
        ({"kind": "hello"}, None, False),
    ]
    return cases


def _python_verdict(message: dict, direction, strict: bool) -> str:
    message = {
        k: ([math.nan if x == "__nan__" else x for x in v] if isinstance(v, list) else v)
        for k, v in message.items()
    }
    try:
        proto.validate(message, direction, strict=strict)
        return "ok"
    except proto.ProtocolError as exc:
        return exc.code


def _to_js(value):
    if isinstance(value, (bytes, bytearray)):
        return {"__bytes__": list(value)}
    if isinstance(value, dict):
        return {k: _to_js(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_to_js(v) for v in value]
    return value


VALIDATE_JS = """async (cases) => {
  const { Protocol } = await import('/app/js/network/protocol.js');
  const protocol = await Protocol.load('/protocol.json');
  const revive = (v) => {
    if (v === '__nan__') return NaN;
    if (Array.isArray(v)) return v.map(revive);
    if (v && typeof v === 'object') {
      if (v.__bytes__) return new Uint8Array(v.__bytes__);
      return Object.fromEntries(Object.entries(v).map(([k, x]) => [k, revive(x)]));
    }
    return v;
  };
  return cases.map(([message, direction, strict]) => {
    try {
      protocol.validate(revive(message), direction, { strict });
      return 'ok';
    } catch (e) {
      return e.code ?? String(e);
    }
  });
}"""

CODEC_JS = """async ([fromServer]) => {
  const { Protocol } = await import('/app/js/network/protocol.js');
  const protocol = await Protocol.load('/protocol.json');
  const decoded = protocol.decode(new Uint8Array(fromServer), 'server_to_client');
  const command = protocol.encode(
    protocol.command(12, 'goto_pixel', { pixel: [320, 240.5], seq: 41 }));
  let tooBig = null;
  try {
    protocol.decode(new Uint8Array(protocol.limits.max_message_bytes + 1));
  } catch (e) {
    tooBig = e.code;
  }
  let trailing = null;
  try { protocol.decode(new Uint8Array([...command, 0xc0])); } catch (e) { trailing = e.code; }
  decoded.route = Array.from(decoded.route);
  return { decoded, command: Array.from(command), tooBig, trailing };
}"""


def test_message_validation_matches_the_server(live_server, open_page):
    page = open_page(live_server())
    cases = _validation_cases()
    expected = [_python_verdict(m, d, s) for m, d, s in cases]
    got = page.page.evaluate(VALIDATE_JS, [[_to_js(m), d, s] for m, d, s in cases])
    mismatches = [
        (case[0].get("type"), e, g)
        for case, e, g in zip(cases, expected, got, strict=True)
        if e != g
    ]
    assert not mismatches, mismatches
    assert expected.count("ok") >= 13 and len(set(expected)) >= 7  # the cases do test something

    # both directions of the codec: the server's encoding decodes in the page, and back
    state = proto.make_drone_state(
        2.0, np.eye(4), (0.1, 0, 0), "goto", 4, route=np.arange(6.0).reshape(2, 3)
    )
    out = page.page.evaluate(CODEC_JS, [list(proto.encode(state))])
    assert out["decoded"]["mode"] == "goto" and out["decoded"]["route"] == [0, 1, 2, 3, 4, 5]
    command = proto.decode(bytes(out["command"]), direction=proto.CLIENT_TO_SERVER)
    assert command == {
        "type": "command",
        "id": 12,
        "name": "goto_pixel",
        "pixel": [320, 240.5],
        "seq": 41,
    }
    assert out["tooBig"] == "message_too_big" and out["trailing"] == "malformed_message"
    assert not page.errors, page.errors


# ---- the page against a live server -----------------------------------------------------------

SPAWNED = "window.dronesim.seen.events.some((e) => e.event === 'spawned')"
# The server spawns the drone as soon as it has a map, which on an idle machine can be before the
# first picture is on screen. To judge that picture without a drone every time, the page's
# client holds its drone messages (drone_state, drone_event) back until released, then hands
# them over in order: releaseDrone() -> how many were held.
HOLD_DRONE_MESSAGES = """() => {
  const c = window.dronesim.client, dispatch = c.dispatchEvent.bind(c), held = [];
  c.dispatchEvent = (event) => {
    if (String(event.detail?.type).startsWith('drone_')) { held.push(event); return true; }
    return dispatch(event);
  };
  window.releaseDrone = () => {
    c.dispatchEvent = dispatch;
    held.forEach((event) => dispatch(event));
    return held.length;
  };
}"""


def test_phone_replay_shows_the_drone_in_ar_and_a_tap_sends_it(live_server, open_page):
    server = live_server()
    page = open_page(server, REPLAY_PATH, **PHONE)
    page.page.evaluate(HOLD_DRONE_MESSAGES)
    page.page.tap("#btn-stream")

    # Before the page hears of the drone: the first picture, no drone paint on it.
    page.page.evaluate("""() => new Promise((resolve) => {
      const c = window.dronesim.client;
      const done = () => {
        c.removeEventListener('pose', done);
        requestAnimationFrame(() => requestAnimationFrame(resolve)); // drawn on screen
      };
      if (window.dronesim.seen.poses > 0) done(); else c.addEventListener('pose', done);
    })""")
    page.screenshot("phone-first-frame.png")
    # The camera picture itself may hold drone-like colours (the demo's random textures): judge
    # the overlay alone, with the picture hidden.
    page.page.evaluate("document.querySelector('.ar-image').style.visibility = 'hidden'")
    first = page.screenshot("phone-first-frame-overlay-only.png")
    page.page.evaluate("document.querySelector('.ar-image').style.visibility = ''")
    seen_first = page.snapshot()
    assert seen_first["droneStates"] == 0 and seen_first["lastDrone"] is None
    assert seen_first["ar"]["shownSeq"] is not None, "no picture on screen"
    st = seen_first["ar"]["stage"]
    rows = slice(int(st["top"]), int(st["top"] + st["height"]))
    area = drone_mask(first)[rows, int(st["left"]) : int(st["left"] + st["width"])]
    assert area.sum() < 10, f"{area.sum()} drone-coloured pixels before the drone exists"
    page.page.evaluate("window.releaseDrone()")

    # Streaming: >= 30 frames, poses back, tracking ok in the HUD, never more than 2 in flight.
    page.wait("window.dronesim.seen.poses >= 30", 90, "30 poses")
    page.wait(
        "document.querySelector('[data-field=tracking]').textContent === 'tracking ok'",
        30,
        "the HUD to show tracking ok",
    )
    s = page.snapshot()
    assert s["sent"] >= 30 and s["poses"] >= 30 and s["states"].get("ok", 0) >= 15, s["states"]
    assert s["counts"]["maxInFlight"] <= 2
    assert s["connection"] == "open" and not [e for e in s["errors"] if e["fatal"]]
    assert "fps" in page.page.inner_text("[data-field=fps]")
    assert "ms" in page.page.inner_text("[data-field=latency]")

    # The drone in the AR view: its colour where its pose projects, gone without the overlay.
    page.wait(SPAWNED + " && window.dronesim.seen.lastDrone", 30, "the drone to spawn")
    spot, added, radius = None, 0, 0.0
    for _ in range(6):
        page.page.tap("#btn-stream")  # stop: the picture holds still
        page.wait("!window.dronesim.streamer.running && !window.dronesim.client.inFlight.size", 15)
        time.sleep(0.5)  # drone states for the last shown frame
        s = page.snapshot()
        spot = expected_drone_screen_point(s)
        if spot is not None and s["ar"]["droneVisible"] and s["lastPose"]["state"] != "lost":
            shot = page.screenshot("phone-ar-drone.png")
            css_per_px = s["ar"]["stage"]["width"] / s["ar"]["colourSize"][0]
            radius = max(25.0, 0.2 * s["ar"]["intrinsics"][0] / spot[2] * css_per_px)  # ~ drone
            near = count_near(drone_mask(shot), spot[:2], radius)
            page.page.evaluate("document.querySelector('.ar-overlay').style.visibility = 'hidden'")
            bare = page.screenshot("phone-ar-without-overlay.png")
            page.page.evaluate("document.querySelector('.ar-overlay').style.visibility = ''")
            # The drone's pixels come from the overlay (the picture may hold a few of its
            # colour too). On a loaded machine the drone state for the shown frame may come
            # late: another still frame is tried rather than the check skipped.
            added = near - count_near(drone_mask(bare), spot[:2], radius)
            if added >= 20:
                break
        page.page.tap("#btn-stream")  # the drone is out of the picture: film on
        time.sleep(1.5)
    assert spot is not None, "the drone never came into the view of a tracked frame"
    assert added >= 20, f"the overlay adds {added} drone-coloured pixels within {radius:.0f} px"
    hud = page.page.inner_text("#hud")
    assert "drone hover" in hud or "drone goto" in hud or "drone manual" in hud, hud

    # Tap the picture: goto_pixel with the shown frame's seq; the drone flies towards the point.
    st, (W, H) = s["ar"]["stage"], s["ar"]["colourSize"]
    u, v = W * 0.5, H * 0.45
    x, y = st["left"] + (u + 0.5) / W * st["width"], st["top"] + (v + 0.5) / H * st["height"]
    page.page.touchscreen.tap(x, y)
    page.wait("window.dronesim.pilot.log.some((c) => c.name === 'goto_pixel')", 5, "goto_pixel")
    command = next(c for c in page.snapshot()["commands"] if c["name"] == "goto_pixel")
    assert command["fields"]["seq"] == s["ar"]["shownSeq"]
    assert command["fields"]["pixel"] == pytest.approx([u, v], abs=1.0)
    approach = wait_for_approach(page, command["id"])
    assert approach["closest"] < approach["start"]
    page.screenshot("phone-after-tap.png")

    # Landscape: both views and every control on screen.
    page.page.set_viewport_size({"width": 844, "height": 390})
    time.sleep(0.5)
    page.screenshot("phone-landscape.png")
    for selector in (
        "#stick-left",
        "#stick-right",
        "#btn-stream",
        "#btn-land",
        ".ar-stage",
        ".map-canvas",
    ):
        box = page.page.locator(selector).bounding_box()
        assert box and box["width"] > 20 and box["height"] > 20, selector
        assert box["x"] >= 0 and box["x"] + box["width"] <= 845, selector
        assert box["y"] >= 0 and box["y"] + box["height"] <= 391, selector
    assert not page.errors, page.errors


def test_desktop_map_reconnect_sticks_and_map_tap(live_server, open_page):
    server = live_server()
    page = open_page(server, REPLAY_PATH, **DESKTOP)
    s = start_replay(page, 30, tap=False)
    session = s["session"]
    assert s["sent"] >= 30 and s["counts"]["maxInFlight"] <= 2

    # The map view shows the fused points, coloured by height.
    page.wait("window.dronesim.seen.mapPoints >= 3000", 30, "3000 map points")
    time.sleep(0.3)
    box = page.page.locator("#map-view").bounding_box()
    page.screenshot("desktop.png")
    rgb = page.screenshot("desktop-map.png", "#map-view")
    background = np.array([0x11, 0x15, 0x1C])
    drawn = np.abs(rgb.astype(int) - background).sum(axis=2) > 40
    assert drawn.sum() > 3000, f"only {drawn.sum()} drawn pixels in the {box} map view"
    hues = cv2.cvtColor(rgb, cv2.COLOR_RGB2HSV)[..., 0][drawn & (rgb.max(axis=2) > 80)]
    assert len(np.unique(hues // 10)) >= 5, "the map is not coloured by height"

    # A lost connection reconnects into the same session and streaming goes on.
    poses = page.snapshot()["poses"]
    page.page.evaluate("window.dronesim.client.ws.close()")
    page.wait(
        "window.dronesim.client.counts.reconnects >= 1 && window.dronesim.client.isOpen "
        f"&& window.dronesim.seen.poses >= {poses + 5}",
        40,
        "a reconnection, 5 more poses",
    )
    s = page.snapshot()
    assert s["session"] == session
    assert "reconnecting" in [e["state"] for e in s["statusLog"]]
    assert page.page.inner_text("[data-field=connection]") == "connected"

    # Sticks: 10-20 Hz while held, zeros on release; the drone flies by hand, then holds.
    page.wait(SPAWNED, 30, "the drone to spawn")
    stick = page.page.locator("#stick-right").bounding_box()
    cx, cy = stick["x"] + stick["width"] / 2, stick["y"] + stick["height"] / 2
    before = len(page.snapshot()["commands"])
    # How long the page itself saw the stick held (a loaded machine delivers the mouse events
    # late: the test's own clock measured 2.2 s for the page's ~1.1 s once).
    page.page.evaluate(
        """() => {
          window.__held = {};
          document.querySelector("#stick-right").addEventListener(
            "pointerdown", () => (window.__held.down = performance.now()), true);
          window.addEventListener("pointerup", () => (window.__held.up = performance.now()), true);
        }"""
    )
    page.page.mouse.move(cx, cy)
    t0 = time.time()
    page.page.mouse.down()
    page.page.mouse.move(cx + stick["width"] * 0.12, cy - stick["height"] * 0.12, steps=3)
    time.sleep(0.8)
    page.page.mouse.up()
    held_s = time.time() - t0  # an upper bound: the events reach the page a little later
    time.sleep(0.3)
    s = page.snapshot()
    held = page.page.evaluate("window.__held")
    page_held_s = (held["up"] - held["down"]) / 1000.0
    assert 0.7 < page_held_s <= held_s + 0.05, (page_held_s, held_s)
    sticks = [c for c in s["commands"][before:] if c["name"] == "sticks"]
    n = len(sticks) - 1  # the last is the release's zeros
    assert 10 * (page_held_s - 0.3) <= n <= 20 * held_s + 2, (len(sticks), page_held_s, held_s)
    assert max(c["fields"]["sticks"][2] for c in sticks) > 0.15  # pitch: forward
    assert max(c["fields"]["sticks"][3] for c in sticks) > 0.15  # roll: to the right
    assert sticks[-1]["fields"]["sticks"] == [0, 0, 0, 0]
    ids = {c["id"] for c in sticks}
    ids = sorted(ids)
    page.wait(
        "window.dronesim.seen.modeLog.some("
        f"(m) => m.mode === 'manual' && {ids}.includes(m.command_id)) || "
        "window.dronesim.seen.events.some("
        f"(e) => e.event === 'collision' && {ids}.includes(e.command_id))",
        5,
        "manual flight (or a collision) from the sticks",
    )
    page.page.click("#btn-hold")
    page.wait("window.dronesim.seen.lastDrone.mode === 'hover'", 5, "hover after hold")

    # A click on the map sends goto with a 3D point of the cloud; the drone approaches it.
    target = page.page.evaluate("""() => {
      const map = window.dronesim.map, THREE_V = map.camera.position.constructor;
      const drone = new THREE_V().setFromMatrixPosition(map.drone.matrix);
      const rect = map.renderer.domElement.getBoundingClientRect();
      const p = new THREE_V();
      let best = null;
      for (let i = 0; i < map.positions.count; i += 7) {
        p.fromArray(map.positions.array, 3 * i);
        const d = p.distanceTo(drone), h = Math.abs(p.clone().sub(drone).dot(map.up));
        if (d < 0.8 || d > 2.2 || h > 0.6) continue;
        const s = p.clone().project(map.camera);
        if (Math.abs(s.x) > 0.85 || Math.abs(s.y) > 0.85 || s.z > 1) continue;
        const score = Math.abs(d - 1.3) + h;
        if (best && score >= best.score) continue;
        best = { score, x: rect.left + (s.x + 1) / 2 * rect.width,
          y: rect.top + (1 - s.y) / 2 * rect.height };
      }
      return best;
    }""")
    assert target is not None, "no map point near the drone on screen"
    page.page.mouse.click(target["x"], target["y"])
    page.wait("window.dronesim.pilot.log.some((c) => c.name === 'goto')", 5, "a goto command")
    command = next(c for c in page.snapshot()["commands"] if c["name"] == "goto")
    assert len(command["fields"]["target"]) == 3
    wait_for_approach(page, command["id"])
    page.screenshot("desktop-after-map-tap.png")

    # Download the fused map (the token goes in the Authorization header).
    with page.page.expect_download(timeout=30_000) as download:
        page.page.click("#btn-download")
    path = download.value.path()
    head = Path(path).read_bytes()[:400]
    assert head.startswith(b"ply") and b"binary_little_endian" in head and b"element vertex" in head
    assert download.value.suggested_filename == f"{session}-map.ply"

    page.page.click("#btn-land")
    page.wait("['landing', 'landed'].includes(window.dronesim.seen.lastDrone.mode)", 5, "landing")

    # A reload reopens the same session (sessionStorage): the map so far comes back from the
    # session's downloads, and frames go on with higher seqs (no bad_sequence).
    last_seq = page.snapshot()["lastPose"]["seq"]
    page.page.reload()
    page.page.wait_for_function(browser.APP_READY, timeout=20_000)
    page.page.click("#btn-stream")
    page.wait(
        "window.dronesim.seen.poses >= 3 && window.dronesim.seen.mapPoints >= 1000",
        40,
        "poses and the restored map after a reload",
    )
    s = page.snapshot()
    assert s["session"] == session
    assert s["mapPoints"] >= s["chunkPoints"] + 1000, "the earlier map was not restored"
    assert s["lastPose"]["seq"] > last_seq
    assert not [e for e in s["errors"] if e["name"] == "bad_sequence"]
    page.screenshot("desktop-after-reload.png")

    # Another tab or device with the token takes the session over (the newest socket wins):
    # this page says so and stays off (reconnecting would take it back, forever), but keeps the
    # session, so that Start takes it back.
    # A frame whose capture was under way when the session moved must not take it back: the
    # next capture is held until the page has let go (CI once caught the page doing just that).
    page.page.evaluate("""() => {
      const source = window.dronesim.streamer.source, capture = source.capture;
      const gate = new Promise((open) => (window.openCaptureGate = open));
      source.capture = async (...args) => {
        const captured = await capture.apply(source, args);
        window.captureHeld = true;
        await gate;
        source.capture = capture;
        window.captureReleased = true;
        return captured;
      };
    }""")
    page.wait("window.captureHeld === true", 10, "a capture held at the gate")
    saved = page.page.evaluate("JSON.parse(sessionStorage.getItem('dronesim.session'))")
    told: list[dict] = []  # what the server says to the other device

    async def take_over() -> Connection:
        other = await Connection.open(
            f"{server.ws_url}/ws/sessions/{saved['id']}", saved["token"], saved["hello"], timeout=10
        )
        other.start(lambda message, _latency: told.append(message))
        return other

    with LoopThread() as loop:  # the protocol client's loop beside Playwright's sync API
        other = loop.run(take_over())
        assert other.welcome["session_id"] == session
        page.wait("window.dronesim.client.state === 'taken_over'", 10, "the page to let go")
        reconnects = page.snapshot()["counts"]["reconnects"]
        page.page.evaluate("window.openCaptureGate()")
        page.wait("window.captureReleased === true", 10, "the held capture to go on")
        time.sleep(2.0)
        s = page.snapshot()
        assert s["counts"]["reconnects"] == reconnects
        assert [e["state"] for e in s["statusLog"][-2:]] == ["open", "taken_over"]
        assert page.page.inner_text("[data-field=connection]") == "taken over"
        assert "took this session over" in page.page.inner_text("#banner")
        loop.run(other.ping(5))  # still ours: the server answers, and said nothing against it
        assert other.receiving and not [m for m in told if m["type"] == "error"], told
        loop.run(other.close())
    page.page.click("#btn-stream")  # Start: this page takes its session back
    page.wait("window.dronesim.client.isOpen", 20, "the page to take its session back")
    assert page.snapshot()["session"] == session
    assert not page.errors, page.errors


def test_replay_of_a_tum_folder_picked_in_the_setup_dialog(
    live_server, open_page, demo_ready, tmp_path
):
    # A TUM-layout folder as a phone user would pick it: PNG colour (re-encoded to JPEG by the
    # page), 16-bit PNG depth at 5000 units per metre, intrinsics.json; the first 24 frames.
    folder = tmp_path / "room_small"
    (folder / "rgb").mkdir(parents=True)
    (folder / "depth").mkdir()
    rgb_rows, depth_rows = [], []
    for line in (demo_ready / "associations.txt").read_text().splitlines()[:24]:
        t, rgb, _, depth = line.split()
        image = cv2.imread(str(demo_ready / rgb))
        cv2.imwrite(str(folder / "rgb" / f"{t}.png"), image)
        (folder / "depth" / f"{t}.png").write_bytes((demo_ready / depth).read_bytes())
        rgb_rows.append(f"{t} rgb/{t}.png")
        depth_rows.append(f"{float(t) + 0.004:.6f} depth/{t}.png")  # associated by nearest time
    (folder / "rgb.txt").write_text("# colour\n" + "\n".join(rgb_rows) + "\n")
    (folder / "depth.txt").write_text("# depth\n" + "\n".join(depth_rows) + "\n")
    (folder / "intrinsics.json").write_text((demo_ready / "intrinsics.json").read_text())

    page = open_page(live_server(), **DESKTOP)
    page.page.click("#btn-menu")
    page.page.set_input_files("#folder-input", folder)
    assert page.page.is_checked('input[name="mode"][value="folder"]')
    page.page.click("#btn-setup-start")
    page.wait("window.dronesim.seen.poses >= 10", 60, "10 poses from the folder")
    s = page.snapshot()
    assert s["hello"]["colour_size"] == [320, 240] and s["hello"]["depth_scale"] == 5000
    assert s["hello"]["client_name"].endswith("room_small")
    assert not s["errors"], s["errors"]  # a PNG colour frame would be corrupt_image
    assert s["states"].get("ok", 0) >= 5
    page.screenshot("desktop-folder-replay.png")
    assert not page.errors, page.errors


def test_a_replay_faster_than_the_server_waits_for_it_and_drops_nothing(live_server, open_page):
    """A recording played at 200 fps, far beyond what the server tracks: the page says recorded
    in its hello, keeps as many frames in flight as the welcome's queued_frames (2) and holds
    the next one until there is room instead of skipping it, says so in the HUD, and neither
    side drops a frame: every seq gets its pose, in order, none missing. Its socket carries the
    frames as they are (no permessage-deflate)."""
    server = live_server()
    page = open_page(server, "/?autostart=demo-small&fps=200", **PHONE)
    page.wait("window.dronesim.seen.poses >= 40", 120, "40 poses")
    page.wait("!document.querySelector('[data-field=held]').hidden", 10, "the HUD to say it waits")
    s = page.snapshot()
    page.page.evaluate("window.dronesim.streamer.stop()")
    assert s["skipped"] == 0, s["skipped"]
    assert s["serverDropped"] == 0, s["serverDropped"]
    assert s["hello"]["recorded"] is True
    queued = page.page.evaluate("window.dronesim.client.welcome.queued_frames")
    assert queued == 2 and s["counts"]["maxInFlight"] == queued, (queued, s["counts"])
    assert s["heldBack"] or s["heldBackMs"] > 0
    # Chromium offers permessage-deflate; the server declines it: frames are not deflated again.
    assert page.page.evaluate("window.dronesim.client.ws.extensions") == ""
    # No gaps: the newest pose's seq is one less than the poses received (seqs start at 0).
    assert s["lastPose"]["seq"] == s["poses"] - 1, (s["lastPose"]["seq"], s["poses"])
    assert not s["errors"], s["errors"]


def _page_with_test_streamer(live_server, open_page, make_streamer_js: str):
    """The page on the small demo with 5 poses, its own Streamer stopped, and a test Streamer
    (window.dronesim.testStreamer) started on the page's client: ``make_streamer_js`` is the body
    of a function of ``app``, ``replay`` (the demo's replay source) and ``Streamer`` that returns
    it."""
    server = live_server()
    page = open_page(server, "/?autostart=demo-small", **PHONE)
    page.wait("window.dronesim.seen.poses >= 5", 120, "5 poses")
    page.page.evaluate(
        """async (body) => {
      const app = window.dronesim, replay = app.source;
      app.streamer.stop();
      const { Streamer } = await import('/app/js/capture/streamer.js');
      app.testStreamer = new Function('app', 'replay', 'Streamer', body)(app, replay, Streamer);
      app.testStreamer.start();
    }""",
        make_streamer_js,
    )
    return page


def test_frames_packed_while_the_next_is_read_are_sent_in_capture_order(live_server, open_page):
    """A live source hands a frame over once its pixels are read ({packing, anchor}) and packs
    it (JPEG, zlib) while the Streamer reads the next one. Here the packing of every other frame
    takes 150 ms and of the rest 5 ms, so later frames finish packing first: the page's Streamer
    must still send them in capture order, with increasing seqs, never more than max_in_flight
    sent or packing at once, and the server must answer them."""
    page = _page_with_test_streamer(
        live_server,
        open_page,
        """
      let order = 0;
      const source = {
        kind: 'live',
        capture: async (tick, t) => {
          const frame = await replay.capture(tick, t), index = order++;
          const ms = index % 2 === 0 ? 150 : 5;
          const packing = new Promise((r) => setTimeout(() => r({ ...frame, index }), ms));
          return { anchor: null, packing };
        },
      };
      const s = new Streamer(app.client, source, { fps: 30 });
      app.sentLog = [];
      app.pendingMax = 0;
      s.addEventListener('sent', (e) => app.sentLog.push([e.detail.index, e.detail.seq]));
      const watch = setInterval(() => {
        app.pendingMax = Math.max(app.pendingMax, app.client.inFlight.size + s.packing);
        if (!s.running) clearInterval(watch);
      }, 1);
      return s;""",
    )
    before = page.snapshot()["poses"]
    # Counted on the test streamer's own frames: poses of the page's frames still in flight
    # when it took over arrive after ``before`` too (a loaded machine: 2 of the 20).
    page.wait(
        f"window.dronesim.seen.poses >= {before + 20}"
        " && window.dronesim.sentLog.length >= 20"
        " && window.dronesim.testStreamer.overlapped >= 3",
        90,
        "20 more poses and 20 frames of the test's source, 3 read while another was packed",
    )
    page.page.evaluate("window.dronesim.testStreamer.stop()")
    sent = page.page.evaluate("window.dronesim.sentLog")
    indices, seqs = [i for i, _ in sent], [q for _, q in sent]
    assert len(sent) >= 20
    assert indices == sorted(indices) and len(set(indices)) == len(indices), indices
    assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs), seqs
    pending_max = page.page.evaluate("window.dronesim.pendingMax")
    assert 2 <= pending_max <= page.page.evaluate("window.dronesim.client.maxInFlight")
    assert not [e for e in page.snapshot()["errors"] if e["fatal"]]


def test_frames_a_source_cannot_give_are_counted_and_capture_goes_on(live_server, open_page):
    """A live source resolves {skip: reason} for a frame without depth or camera image (normal
    while ARCore re-initialises). The capture loop counts it and goes on: here a source that
    gives every 3rd frame without depth, driving the page's own Streamer and client (the live
    source on an emulated AR device: tests/browser/test_webxr_live.py)."""
    page = _page_with_test_streamer(
        live_server,
        open_page,
        """
      const flaky = {
        kind: 'live',
        capture: (tick, t) => (tick % 3 === 0 ? Promise.resolve({ skip: 'no depth' })
                                              : replay.capture(tick, t)),
      };
      return new Streamer(app.client, flaky, { fps: 15 });""",
    )
    before = page.snapshot()["poses"]
    page.wait(
        f"window.dronesim.seen.poses >= {before + 15}"
        " && (window.dronesim.testStreamer.unavailable['no depth'] ?? 0) >= 4",
        90,
        "15 more poses and 4 frames without depth",
    )
    s = page.page.evaluate(
        "({running: window.dronesim.testStreamer.running, "
        "unavailable: window.dronesim.testStreamer.unavailable})"
    )
    page.page.evaluate("window.dronesim.testStreamer.stop()")
    assert s["running"], "capture stopped on a frame without depth"
    assert s["unavailable"].get("no depth", 0) >= 4, s["unavailable"]
    assert not [e for e in page.snapshot()["errors"] if e["fatal"]]


def test_the_page_says_when_tracking_recovers_and_when_a_pose_is_only_a_guess(
    live_server, open_page, shared_data, tmp_path
):
    """A recording that jumps to a view the map does not have and walks back (synthetic_room0,
    as tests/server/test_recovery_server.py): while the server tracks a map segment, the AR view
    says the pose is a rough guess and the HUD says so beside the state; once the segment merges,
    the hint goes and the HUD says tracking is back in the map."""
    source = shared_data / "synthetic_room0"
    frames = [line.split() for line in (source / "associations.txt").read_text().splitlines()]
    walk = list(range(0, 40, 2)) + list(range(74, 150, 2)) + list(range(147, 0, -3))
    folder = tmp_path / "jump"
    (folder / "rgb").mkdir(parents=True)
    (folder / "depth").mkdir()
    rgb_rows, depth_rows = [], []
    for k, i in enumerate(walk):
        _, rgb, _, depth = frames[i]
        t = f"{1700000000 + k / 30:.6f}"
        (folder / "rgb" / f"{t}.jpg").write_bytes((source / rgb).read_bytes())
        (folder / "depth" / f"{t}.png").write_bytes((source / depth).read_bytes())
        rgb_rows.append(f"{t} rgb/{t}.jpg")
        depth_rows.append(f"{t} depth/{t}.png")
    (folder / "rgb.txt").write_text("\n".join(rgb_rows) + "\n")
    (folder / "depth.txt").write_text("\n".join(depth_rows) + "\n")
    (folder / "intrinsics.json").write_text((source / "intrinsics.json").read_text())

    page = open_page(live_server(), **DESKTOP)
    page.page.click("#btn-menu")
    page.page.set_input_files("#folder-input", folder)
    page.page.click("#btn-setup-start")
    in_segment = """(() => {
      const pose = window.dronesim.seen.lastPose;
      const hint = document.querySelector('#ar-view .segment-hint');
      const hud = document.querySelector('[data-field=tracking]').textContent;
      return pose?.recovery === 'segment' && getComputedStyle(hint).display === 'block'
        && hud.includes('placed roughly');
    })()"""
    page.wait(in_segment, 120, "the page to show a pose in a map segment")
    page.screenshot("desktop-tracking-segment.png")
    page.wait("(window.dronesim.seen.recovery.merged ?? 0) >= 1", 120, "the segment to merge")
    page.wait(
        "window.dronesim.seen.lastPose.recovery !== 'segment' && getComputedStyle("
        "document.querySelector('#ar-view .segment-hint')).display === 'none'",
        10,
        "the hint to go once merged",
    )
    s = page.snapshot()
    assert s["recovery"]["segment"] > 5 and s["recovery"]["merged"] == 1
    assert not s["errors"], s["errors"]
    assert not page.errors, page.errors
