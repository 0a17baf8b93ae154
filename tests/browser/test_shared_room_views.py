"""The other pilots' drones of a shared room in the page's AR and FPV views, in a real browser
(each view alone on the page, fed a hand-made `room` message as session/room.js parses it):

* AR: real surfaces hide the other pilots' drones as they hide this page's own (occlusion.js):
  a frame's depth (or, without it, the map's mesh) puts a surface 1.5 m away over the left half
  of the view and one 2.5 m away over the right half; one other drone 2 m away on the left is
  behind its surface and hidden, one on the right is in front of its surface and shows; without
  occlusion both show. With this page's drone in the picture too (behind its surface, so hidden),
  and without it. The depth quad's screen boxes (one per drone, merged where that draws fewer
  pixels) are checked on their own too.
* FPV: the view draws an other pilot's drone in front of the own drone's camera, in its colour,
  where the camera's projection (computed here from FPV_CAMERA) puts it; gone when its pilot's
  drone is. The page's FPV view follows the room messages the page's client gets.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from tests.support.browser import canvas_rgb, count_near, drone_mask

F, CX, CY, W, H = 200.0, 159.5, 119.5, 320, 240  # the AR view's camera in these tests
# Paints of the other pilots (room_pilots.js COLOURS by index in the room): 1 orange, 2 lime.
PAINT = {1: 0xFF9A00, 2: 0x7CFF00}
TOP_TO_CAMERA = [1.0, 0.0, 0.0, 0.0]  # 180 degrees about x: a drone shows its top to the camera
OTHERS = {1: [-0.7, 0.0, 2.0], 2: [0.7, 0.0, 2.0]}  # camera = world: behind 1.5 m, before 2.5 m
OWN = [-0.9, -0.6, 3.0]  # this page's drone, when drawn: behind the 1.5 m surface
SURFACES_M = (1.5, 2.5)  # left half, right half


def _paint(rgb: np.ndarray, colour: int) -> np.ndarray:
    """Pixels near a drone paint's hue (lit or in shade)."""
    want = np.array([(colour >> 16) & 255, (colour >> 8) & 255, colour & 255], np.uint8)
    hsv = cv2.cvtColor(rgb, cv2.COLOR_RGB2HSV).astype(int)
    hue = int(cv2.cvtColor(want[None, None], cv2.COLOR_RGB2HSV)[0, 0, 0])
    dh = np.minimum(abs(hsv[..., 0] - hue), 180 - abs(hsv[..., 0] - hue))
    return (dh <= 6) & (hsv[..., 1] > 150) & (hsv[..., 2] > 90)


def _room(others: dict, modes: dict | None = None) -> dict:
    """A room message: pilot 0 is this page, pilots 1.. fly the drones at ``others`` (world)."""
    n = 1 + len(others)
    modes = modes or {}
    drones = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]
    for i in range(1, n):
        drones += [float(v) for v in (*others[i][0], *others[i][1])]
    return dict(type="room", pilots=["me"] + [f"p{i}" for i in range(1, n)], you=0,
                placed=[True] * n, modes=["hover"] + [modes.get(i, "hover") for i in range(1, n)],
                drones=drones, cameras=[0.0] * 7 * n)  # fmt: skip


# The AR view alone on the page, its shown frame's camera at the world's origin (intrinsics F,
# CX, CY for a W x H picture); the other pilots from a room message; this page's drone or none;
# the surfaces as the frame's depth image (source "depth") or as the map's mesh (two walls, the
# frame without depth: "mesh"). -> the overlay's pixels (PNG), what the view says it drew.
AR_JS = """async ([message, own, source, enabled, surfaces, intrinsics, size]) => {
  const { ARView } = await import('/app/js/views/ar_view.js');
  const { roomPilots } = await import('/app/js/session/room.js');
  const THREE = await import('three');
  const [W, H] = size;
  const box = document.createElement('div');
  box.style.cssText = `position:fixed;left:0;top:0;width:${W}px;height:${H}px;z-index:99`;
  document.body.append(box);
  const ar = new ARView(box);
  ar.renderer.setPixelRatio(1);
  ar.setCamera(intrinsics, [W, H]);
  ar.renderer.setSize(W, H);
  ar.showFrame(null, 1, [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]);
  // body z (up) -> camera -z: the drone shows its top to the camera
  if (own) {
    const [x, y, z] = own;
    const T_world_drone = [1, 0, 0, x, 0, -1, 0, y, 0, 0, -1, z, 0, 0, 0, 1];
    ar.setDroneState({ mode: 'hover', T_world_drone });
  }
  ar.setRoom(roomPilots(message));
  ar.occlusion.enabled = enabled;
  if (source === 'depth') {
    const [dw, dh] = [160, 120];
    const depth = new Float32Array(dw * dh);
    for (let y = 0; y < dh; y++) {
      for (let x = 0; x < dw; x++) depth[y * dw + x] = surfaces[(x + 0.5) / dw < 0.5 ? 0 : 1];
    }
    ar.occlusion.setDepth(depth, dw, dh, 1);
  } else { // two walls facing the camera, split at x = 0 (world = the frame's camera frame)
    const wall = (x0, x1, z) => [x0, -5, z, x1, -5, z, x1, 5, z, x0, 5, z];
    const g = new THREE.BufferGeometry();
    const walls = [...wall(-5, 0, surfaces[0]), ...wall(0, 5, surfaces[1])];
    g.setAttribute('position', new THREE.Float32BufferAttribute(walls, 3));
    g.setIndex([0, 1, 2, 0, 2, 3, 4, 5, 6, 4, 6, 7]);
    ar.occlusion.setMesh(g);
  }
  ar.render(0);
  const canvas = document.createElement('canvas');
  canvas.width = W; canvas.height = H;
  canvas.getContext('2d').drawImage(ar.renderer.domElement, 0, 0, W, H);
  const out = { png: canvas.toDataURL('image/png'), others: ar.lastDraw.others,
    source: ar.lastDraw.occlusion, boxes: ar.lastDraw.occlusionBoxes };
  ar.renderer.dispose();
  box.remove();
  return out;
}"""


def _ar(page, own: bool, source: str, enabled: bool) -> dict:
    message = _room({i: (p, TOP_TO_CAMERA) for i, p in OTHERS.items()})
    out = page.page.evaluate(
        AR_JS,
        [message, OWN if own else None, source, enabled, list(SURFACES_M), [F, F, CX, CY], [W, H]],
    )
    rgb = canvas_rgb(
        out["png"], f"room-ar-{source}{'-own' if own else ''}{'' if enabled else '-off'}.png"
    )
    counts = {}
    for item in out["others"]:
        x, y, z = OTHERS[item["index"]]
        expected = [F * x / z + CX, F * y / z + CY]  # the page's pixel is not trusted
        assert np.allclose(item["pixel"], expected, atol=0.5), (item, expected)
        colour = PAINT[item["index"]]
        counts[item["index"]] = count_near(
            _paint(rgb, colour), (expected[0] + 0.5, expected[1] + 0.5), 45
        )
    assert sorted(counts) == [1, 2], out["others"]
    if own:
        x, y, z = OWN
        counts["own"] = count_near(
            drone_mask(rgb), (F * x / z + CX + 0.5, F * y / z + CY + 0.5), 30
        )
    return {**out, "counts": counts}


def test_real_surfaces_hide_the_other_pilots_drones_in_ar(live_server, open_page):
    page = open_page(live_server())
    for own in (False, True):
        for source in ("depth", "mesh"):
            shown = _ar(page, own, source, enabled=False)["counts"]
            seen = _ar(page, own, source, enabled=True)
            c = seen["counts"]
            what = (own, source, shown, c)
            assert seen["source"] == source, (what, seen["source"])
            # Without occlusion each drone shows its paint where it projects.
            assert shown[1] >= 40 and shown[2] >= 40, what
            # Drone 1 (2 m) is behind the left surface (1.5 m): hidden; drone 2 (2 m) is in front
            # of the right one (2.5 m): shown as without occlusion.
            assert c[1] <= 0.05 * shown[1], what
            assert c[2] >= 0.8 * shown[2], what
            if own:  # this page's drone (3 m) behind its surface (1.5 m), as before
                assert shown["own"] >= 20 and c["own"] <= 0.05 * shown["own"], what
            # The depth quad's boxes: the two others' apart, this page's merged with drone 1's
            # (they overlap); the mesh needs none.
            assert seen["boxes"] == (2 if source == "depth" else 0), (what, seen["boxes"])

    # Boxes merge where the box around them has no more pixels than they have together.
    merged = page.page.evaluate(MERGE_JS)
    assert merged["apart"] == [[-1, -1, -0.5, -0.5], [0.5, 0.5, 1, 1]], merged
    assert merged["overlapping"] == [[-0.5, -0.5, 0.2, 0.2]], merged
    assert merged["corners"] == [[0, 0, 0.5, 0.5], [0.4, 0.4, 0.9, 0.9]], merged  # 1 % overlap
    assert merged["chain"] == [[-1, -0.1, 1, 0.1]], merged  # a with c, then b
    assert merged["behind"] is None and merged["inside"] == [-1, -1, 1, 1], merged
    assert not page.errors, page.errors


MERGE_JS = """async () => {
  const { droneBox, mergeBoxes } = await import('/app/js/views/occlusion.js');
  const THREE = await import('three');
  const P = new THREE.Matrix4().makePerspective(-0.1, 0.1, 0.1, -0.1, 0.1, 100);
  return {
    apart: mergeBoxes([[-1, -1, -0.5, -0.5], [0.5, 0.5, 1, 1]]),
    overlapping: mergeBoxes([[-0.5, -0.5, 0.1, 0.1], [-0.4, -0.4, 0.2, 0.2]]),
    corners: mergeBoxes([[0, 0, 0.5, 0.5], [0.4, 0.4, 0.9, 0.9]]),
    chain: mergeBoxes([[-1, -0.1, -0.3, 0.1], [0.3, -0.1, 1, 0.1], [-0.35, -0.1, 0.35, 0.1]]),
    behind: droneBox(new THREE.Vector4(0, 0, 2, 2).applyMatrix4(P), P),
    inside: droneBox(new THREE.Vector4(0, 0, -0.1, 1).applyMatrix4(P), P),
  };
}"""


# The FPV view alone on the page (W x H), the own drone at T_world_drone (row-major), the other
# pilots from a room message. -> its pixels (PNG), and the others it says it drew.
FPV_JS = """async ([message, T_world_drone, size]) => {
  const { FPVView } = await import('/app/js/views/fpv_view.js');
  const { roomPilots } = await import('/app/js/session/room.js');
  const [W, H] = size;
  const box = document.createElement('div');
  box.style.cssText = `position:fixed;left:0;top:0;width:${W}px;height:${H}px;z-index:99`;
  document.body.append(box);
  const fpv = new FPVView(box);
  fpv.renderer.setPixelRatio(1);
  fpv.renderer.setSize(W, H);
  fpv.setDroneState({ mode: 'hover', T_world_drone });
  fpv.setRoom(roomPilots(message));
  fpv.render();
  const canvas = document.createElement('canvas');
  canvas.width = W; canvas.height = H;
  canvas.getContext('2d').drawImage(fpv.renderer.domElement, 0, 0, W, H);
  const out = { png: canvas.toDataURL('image/png'), others: fpv.lastDraw.others };
  fpv.renderer.dispose();
  box.remove();
  return out;
}"""


def _fpv_view_point(T_world_drone: np.ndarray, p_world: np.ndarray) -> np.ndarray:
    """Where the FPV camera (fpv_view.js FPV_CAMERA: on the nose at (0.08, 0, 0.02) in the body,
    looking along body x, tilted up 15 degrees, 100 degrees wide, 4:3) sees a world point:
    view [x, y] in 0..1 (x right, y down)."""
    t = math.radians(15)
    # GL camera axes (x right, y up, z back) in the body (x forward, y left, z up), tilted up.
    level = np.array([[0, 0, -1], [-1, 0, 0], [0, 1, 0]], float)  # columns: camera x, y, z
    tilt = np.array([[1, 0, 0], [0, math.cos(t), -math.sin(t)], [0, math.sin(t), math.cos(t)]])
    R_body_camera = level @ tilt
    p_body = T_world_drone[:3, :3].T @ (p_world - T_world_drone[:3, 3])
    p = R_body_camera.T @ (p_body - np.array([0.08, 0.0, 0.02]))
    assert p[2] < 0, p  # in front of the camera
    tan_x = math.tan(math.radians(50))
    ndc = np.array([p[0] / -p[2] / tan_x, p[1] / -p[2] / (tan_x / (4 / 3))])
    return np.array([0.5 + 0.5 * ndc[0], 0.5 - 0.5 * ndc[1]])


def test_the_fpv_view_draws_the_other_pilots_drones(live_server, open_page):
    page = open_page(live_server())
    # The own drone somewhere in the room, yawed 90 degrees (body x along world y).
    T_world_drone = np.array([[0, -1, 0, 1.0], [1, 0, 0, 2.0], [0, 0, 1, 0.5], [0, 0, 0, 1]], float)
    # The other drone 1.2 m ahead, 0.3 m to the right and up, its top towards the camera
    # (its body z along the own drone's -x: 90 degrees about the world's x here).
    ahead = T_world_drone[:3, :3] @ np.array([1.2, -0.3, 0.3]) + T_world_drone[:3, 3]
    facing = [math.sqrt(0.5), 0.0, 0.0, math.sqrt(0.5)]
    expected = _fpv_view_point(T_world_drone, ahead) * [W, H]
    counts = {}
    for mode in ("hover", "none"):
        message = _room({1: (ahead, facing)}, {1: mode})
        out = page.page.evaluate(FPV_JS, [message, T_world_drone.flatten().tolist(), [W, H]])
        rgb = canvas_rgb(out["png"], f"room-fpv-{mode}.png")
        counts[mode] = count_near(_paint(rgb, PAINT[1]), expected, 30)
        if mode == "hover":
            (drawn,) = out["others"]
            assert drawn["index"] == 1 and np.allclose(drawn["position"], ahead, atol=1e-5)
            assert np.allclose(np.array(drawn["view"]) * [W, H], expected, atol=1.0), (
                drawn,
                expected,
            )
        else:
            assert out["others"] == [], out["others"]
    # In its colour where the camera sees it; nothing there once its pilot has no drone.
    assert counts["hover"] >= 60 and counts["none"] <= 2, (counts, expected)

    # The page's own FPV view follows the room messages its client gets.
    message = _room({1: (ahead, facing)})
    page.page.evaluate(
        """([m, T]) => { const app = window.dronesim;
      app.client.dispatchEvent(new CustomEvent('room', {detail: m}));
      app.fpv.setDroneState({ mode: 'hover', T_world_drone: T });
      app.fpv.render(); }""",
        [message, T_world_drone.flatten().tolist()],
    )
    (drawn,) = page.snapshot()["room"]["fpv_others"]
    assert drawn["index"] == 1 and drawn["view"] is not None, drawn
    assert not page.errors, page.errors
