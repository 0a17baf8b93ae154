"""The page's views beside AR and map, in a real browser against a real server on loopback:

* Occlusion in AR: the small demo replayed on a phone viewport, the picture held on a frame
  that looks at the demo room's table; the drone sent to a point the table hides from that
  camera (found in the synthetic room's own geometry, by ray casting) shows its paint with
  occlusion off and loses it with occlusion on; sent to a point in front of the table, it shows
  with occlusion on.
* FPV: the view selector's FPV draws the room from the fused mesh (most of the picture is not
  background), and the picture changes when the drone yaws (left stick); the mesh is downloaded
  at a bounded rate.

Screenshots go to the test's tmp dir.
"""

from __future__ import annotations

import time
from pathlib import Path

import cv2
import numpy as np

from server.simulation.config import SimulationConfig
from tests.support.browser import (
    PHONE,
    REPLAY_PATH,
    count_near,
    drone_mask,
    expected_drone_screen_point,
    start_replay,
)

SPAWNED = "window.dronesim.seen.events.some((e) => e.event === 'spawned')"
# Frames of the small demo whose camera sees the table by the -y wall with free space behind
# it (found by ray casting the synthetic room; the search below picks the point per frame).
TABLE_FRAMES = range(80, 90)
DRONE_PAINT_RADIUS_M = (
    0.17  # centre to the tips of the magenta arms (client_web/js/views/drone_model.js)
)


def _shot(page, path: Path) -> np.ndarray:
    data = page.page.screenshot(path=str(path))
    return cv2.cvtColor(
        cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB
    )


# The held frame's depth set aside (as when a live XR frame has none) and put back.
USE_MESH = """() => { const ar = window.dronesim.ar;
  window.heldDepth = ar.occlusion.depth ?? window.heldDepth;
  ar.occlusion.clearDepth();
  ar.dirty = true; }"""
USE_DEPTH = """() => { const ar = window.dronesim.ar;
  ar.occlusion.depth = window.heldDepth;
  ar.dirty = true; }"""


def _hidden_and_front_points(index: int) -> tuple[np.ndarray, np.ndarray, float, int]:
    """In the demo room's own frame, for the camera of frame ``index``: the free point (0.3 m
    clear of every surface, in the picture) whose drone-sized disc is most hidden by a surface,
    a free point on the same ray in front of that surface, the hidden share, and the id of the
    geometry that hides it."""
    import open3d as o3d

    from server.datasets.demo import build_scene, camera_poses
    from server.transport.routes_client import DEMO_PRESETS

    spec = DEMO_PRESETS["small"]
    scene, _ = build_scene(spec)
    T = camera_poses(spec)[index]
    grid = np.mgrid[-2.8:2.8:0.1, -2.3:2.3:0.1, 0.25:2.4:0.05].reshape(3, -1).T.astype(np.float32)
    grid = grid[scene.compute_distance(o3d.core.Tensor(grid)).numpy() >= 0.28]
    in_camera = (grid - T[:3, 3]) @ T[:3, :3]
    z = in_camera[:, 2]
    u = spec.fx * in_camera[:, 0] / np.maximum(z, 1e-6) + spec.cx
    v = spec.fy * in_camera[:, 1] / np.maximum(z, 1e-6) + spec.cy
    m = 40
    grid = grid[(z > 1.0) & (u > m) & (u < spec.width - m) & (v > m) & (v < spec.height - m)]
    angles = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    r = DRONE_PAINT_RADIUS_M
    disc = np.concatenate(
        [[[0, 0, 0]], np.stack([r * np.cos(angles), r * np.sin(angles), 0 * angles], 1)]
    )
    samples = grid[:, None, :] + disc[None]
    rays = samples - T[:3, 3]
    dist = np.linalg.norm(rays, axis=-1)
    origins = np.broadcast_to(T[:3, 3], rays.shape)
    cast = scene.cast_rays(
        o3d.core.Tensor(
            np.concatenate([origins, rays / dist[..., None]], -1).reshape(-1, 6).astype(np.float32)
        )
    )
    hit = cast["t_hit"].numpy().reshape(dist.shape)
    hidden = (hit < dist - 0.15).mean(axis=1)
    best = int(np.argmax(hidden - 0.01 * dist[:, 0]))  # most hidden, then nearest
    behind = grid[best]
    direction = rays[best, 0] / dist[best, 0]
    front = T[:3, 3] + direction * (0.55 * hit[best, 0])
    surface = int(cast["geometry_ids"].numpy().reshape(dist.shape)[best, 0])
    return behind, front, float(hidden[best]), surface


def _hold_on(page, frames: range) -> dict:
    """Stop the replay on the first frame of ``frames`` that goes out; wait until it is on
    screen (tracked, its depth in the occluder). -> the page's snapshot, plus the demo index."""
    page.page.evaluate(
        """(frames) => {
      const app = window.dronesim, s = app.streamer;
      window.heldSeq = null;
      window.heldIndex = null;
      const onSent = (e) => {
        if (!frames.includes(e.detail.index)) return;
        s.removeEventListener('sent', onSent);
        s.stop();
        window.heldSeq = e.detail.seq;
        window.heldIndex = e.detail.index;
      };
      s.addEventListener('sent', onSent);
      if (!s.running) s.start();
    }""",
        list(frames),
    )
    page.wait(
        "window.heldSeq !== null && window.dronesim.ar.frame?.seq === window.heldSeq"
        " && window.dronesim.ar.occlusion.depth?.seq === window.heldSeq",
        60,
        "the replay to show a frame that sees the table",
    )
    snap = page.snapshot()
    snap["heldIndex"] = page.page.evaluate("window.heldIndex")
    return snap


def _fly_to(page, target_world, timeout_s: float = 40.0) -> None:
    command = page.page.evaluate(
        "(p) => window.dronesim.pilot.goto(p)", [float(v) for v in target_world]
    )
    assert command is not None, "the page could not send goto"
    page.wait(
        "window.dronesim.seen.events.some((e) => e.event === 'arrived'"
        f" && e.command_id === {command})",
        timeout_s,
        f"the drone to arrive at {np.round(target_world, 2).tolist()}",
    )
    errors = [e for e in page.snapshot()["errors"] if e.get("command_id") == command]
    assert not errors, errors
    time.sleep(0.5)  # settled; the overlay redrawn with the latest state


def _mesh_hidden_share(page, T_world_camera) -> float:
    """The share of the drone's disc (its arms' reach, DRONE_PAINT_RADIUS_M, in its own level
    body plane) that the page's map mesh hides from the camera at T_world_camera (16 numbers,
    row-major), with the occluder's bias (client_web/js/views/occlusion.js OCCLUSION_BIAS: 4 cm
    + 2 % of the distance)."""
    import open3d as o3d

    mesh = page.page.evaluate(
        """() => { const g = window.dronesim.mapMesh.geometry;
      return { p: Array.from(g.getAttribute('position').array), i: Array.from(g.index.array),
               drone: window.dronesim.seen.lastDrone.T_world_drone }; }"""
    )
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        np.asarray(mesh["p"], np.float32).reshape(-1, 3),
        np.asarray(mesh["i"], np.uint32).reshape(-1, 3),
    )
    T = np.asarray(T_world_camera, float).reshape(4, 4)
    T_world_drone = np.asarray(mesh["drone"], float).reshape(4, 4)
    angles = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    arms = np.stack([np.cos(angles), np.sin(angles), 0 * angles], 1) * DRONE_PAINT_RADIUS_M
    disc = (
        np.concatenate([[[0.0, 0.0, 0.0]], arms]) @ T_world_drone[:3, :3].T + T_world_drone[:3, 3]
    )
    rays = disc - T[:3, 3]
    dist = np.linalg.norm(rays, axis=1)
    origins = np.broadcast_to(T[:3, 3], rays.shape)
    cast = scene.cast_rays(
        o3d.core.Tensor(np.concatenate([origins, rays / dist[:, None]], 1).astype(np.float32))
    )
    hit = cast["t_hit"].numpy()
    return float(np.mean(hit < dist - (0.04 + 0.02 * dist)))


def _drone_paint(page, tmp_path: Path, name: str) -> tuple[int, float]:
    """Drone-coloured pixels of the overlay alone (the picture hidden: the demo's random
    textures hold a few such colours) near where the drone's centre projects."""
    page.page.evaluate("document.querySelector('.ar-image').style.visibility = 'hidden'")
    page.page.evaluate("new Promise((r) => requestAnimationFrame(() => requestAnimationFrame(r)))")
    time.sleep(0.2)
    snap = page.snapshot()
    spot = expected_drone_screen_point(snap)
    assert spot is not None, f"the drone is not in the held picture: {snap['lastDrone']}"
    shot = _shot(page, tmp_path / f"{name}-overlay.png")
    page.page.evaluate("document.querySelector('.ar-image').style.visibility = ''")
    _shot(page, tmp_path / f"{name}.png")
    css_per_px = snap["ar"]["stage"]["width"] / snap["ar"]["colourSize"][0]
    radius = max(
        20.0, 1.3 * DRONE_PAINT_RADIUS_M * snap["ar"]["intrinsics"][0] / spot[2] * css_per_px
    )
    return count_near(drone_mask(shot), spot[:2], radius), spot[2]


def test_ar_occlusion_hides_the_drone_behind_the_demo_table(live_server, open_page, tmp_path):
    # Unobserved space counts as blocked by default, and the space behind the table is what the
    # camera never saw: the drone may fly there in this test.
    server = live_server(simulation=SimulationConfig(unknown_is_free=True))
    page = open_page(server, REPLAY_PATH + "&view=ar", **PHONE)
    # A whole pass of the replay (90 frames) and back into the frames that see the table: the
    # map (and so the drone's flight space) then reaches the room's corner behind it.
    start_replay(page, 100, tap=True)
    page.wait(SPAWNED, 30, "the drone to spawn")

    for _ in range(3):
        held = _hold_on(page, TABLE_FRAMES)
        if held["lastPose"]["seq"] == held["ar"]["shownSeq"] and held["lastPose"]["state"] == "ok":
            break
    assert held["lastPose"]["state"] == "ok", held["lastPose"]
    behind, front, hidden_share, surface = _hidden_and_front_points(held["heldIndex"])
    assert hidden_share >= 0.9 and surface == 6, (hidden_share, surface)  # 6: the table's top

    # Demo room frame -> the session's world, through the held frame's camera (tracked pose).
    from server.datasets.demo import camera_poses
    from server.transport.routes_client import DEMO_PRESETS

    T_demo_camera = camera_poses(DEMO_PRESETS["small"])[held["heldIndex"]]
    T_world_camera = np.array(held["lastPose"]["T_world_camera"]).reshape(4, 4)
    T_world_demo = T_world_camera @ np.linalg.inv(T_demo_camera)

    def world(p):
        return (T_world_demo @ np.append(p, 1.0))[:3]

    _fly_to(page, world(behind))
    assert page.snapshot()["occlusion"]["source"] == "depth"
    page.page.tap("#btn-occlusion")  # off
    shown, z_behind = _drone_paint(page, tmp_path, "behind-table-occlusion-off")
    assert not page.snapshot()["occlusion"]["enabled"]
    page.page.tap("#btn-occlusion")  # on
    hidden, _ = _drone_paint(page, tmp_path, "behind-table-occlusion-on")
    s = page.snapshot()
    assert s["occlusion"] == {**s["occlusion"], "enabled": True, "source": "depth"}
    assert shown >= 20, f"without occlusion the drone {z_behind:.2f} m away shows only {shown} px"
    assert hidden <= 0.2 * shown, f"behind the table {hidden} of {shown} drone pixels still show"

    # Without the frame's depth (live AR while ARCore has none), the fused mesh hides it.
    # A mesh of the map as it is now: one fetched earlier (the view wants the mesh whenever
    # depth is missing for a second, e.g. before the first frames) may predate the table's part
    # of the map, and waiting for any mesh then used it (one CI run showed 61 of 65 px).
    asked = page.page.evaluate(
        "() => { const m = window.dronesim.mapMesh; const n = m.downloads; m.wanted = true;"
        " m.nextAllowed = 0; m.loadedAtPoints = -1; m.poll(); return n; }"
    )
    page.wait(
        f"(m => m.downloads > {asked} && !m.pending && m.geometry !== null)"
        "(window.dronesim.mapMesh)",
        40,
        "a mesh of the map as it is now",
    )
    page.page.evaluate(USE_MESH)
    by_mesh, _ = _drone_paint(page, tmp_path, "behind-table-occlusion-mesh")
    assert page.snapshot()["occlusion"]["source"] == "mesh"
    # The mesh is the map, fused from tracked poses, drawn from the held frame's tracked pose:
    # on the replay's second pass (it wraps from its last frame to its first, and the live
    # tracker finds itself again with an error that depends on timing) it can sit a few cm off
    # the picture, enough on a loaded machine to hide none of a drone just behind the table's
    # edge that depth hides (CI: 61 of 65 px shown). So what the page shows is held against the
    # mesh's own geometry seen from that pose: hidden where the mesh hides the drone's disc,
    # shown where it does not. It is also coarser than depth (the map's voxels, eroded edges):
    # a good part hidden, not all (100 % in most runs, 42 % in one).
    mesh_hides = _mesh_hidden_share(page, held["lastPose"]["T_world_camera"])
    print(f"the mesh hides {mesh_hides:.0%} of the drone's disc from the held pose")
    if mesh_hides >= 0.6:  # 85 % on a quiet machine (the page then hid 100 %)
        assert by_mesh <= 0.7 * shown, f"behind the table {by_mesh} of {shown} px show (mesh)"
    elif mesh_hides <= 0.3:
        assert by_mesh >= 0.5 * shown, (
            f"the mesh hides {mesh_hides:.0%}, the page {by_mesh}/{shown}"
        )

    page.page.evaluate(USE_DEPTH)
    _fly_to(page, world(front))
    in_front, z_front = _drone_paint(page, tmp_path, "before-table-occlusion-on")
    assert page.snapshot()["occlusion"]["source"] == "depth"
    assert z_front < z_behind - 0.5
    assert in_front >= 20, f"in front of the table the drone shows only {in_front} px"
    page.page.evaluate(USE_MESH)
    in_front_mesh, _ = _drone_paint(page, tmp_path, "before-table-occlusion-mesh")
    assert page.snapshot()["occlusion"]["source"] == "mesh"
    assert in_front_mesh >= 0.8 * in_front, (in_front_mesh, in_front)
    print(
        f"drone-coloured px: behind the table {shown} (occlusion off), {hidden} (depth),"
        f" {by_mesh} (mesh) at {z_behind:.2f} m; in front {in_front} (depth),"
        f" {in_front_mesh} (mesh) at {z_front:.2f} m"
    )
    assert not page.errors, page.errors


def test_fpv_view_draws_the_room_from_the_drone(live_server, open_page, tmp_path):
    server = live_server()
    page = open_page(server, REPLAY_PATH, **PHONE)
    start_replay(page, 20, tap=True)
    page.wait(SPAWNED + " && window.dronesim.seen.lastDrone", 30, "the drone to spawn")
    t0 = time.time()
    page.page.tap("[data-view=fpv]")
    page.wait("window.dronesim.snapshot().fpv.drawn", 40, "the FPV view to draw the mesh")
    page.page.evaluate("new Promise((r) => requestAnimationFrame(() => requestAnimationFrame(r)))")
    s = page.snapshot()
    # Asked for once the server said its map has a surface: never a 409 on the way.
    assert s["mesh"]["surface"] is True and s["mesh"]["failures"] == 0, s["mesh"]
    assert s["fpv"]["triangles"] >= 1000, s["fpv"]
    assert page.page.locator("#ar-view").is_hidden() and page.page.locator("#map-view").is_hidden()

    def picture(name: str) -> np.ndarray:
        data = page.page.locator(".fpv-canvas").screenshot(path=str(tmp_path / name))
        return cv2.cvtColor(
            cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB
        )

    first = picture("fpv-first.png")
    sky = np.array([0x27, 0x31, 0x3F])
    room = np.abs(first.astype(int) - sky).sum(axis=-1) > 30
    assert room.mean() >= 0.3, f"only {room.mean():.0%} of the FPV picture shows the room"

    # Yaw with the left stick held to the left: the drone turns, and the picture with it.
    start = np.array(s["fpv"]["cameraForward"])
    stick = page.page.locator("#stick-left").bounding_box()
    cx, cy = stick["x"] + stick["width"] / 2, stick["y"] + stick["height"] / 2
    page.page.mouse.move(cx, cy)
    page.page.mouse.down()
    page.page.mouse.move(cx - stick["width"] * 0.4, cy, steps=3)
    try:
        page.wait(
            "(() => { const f = window.dronesim.snapshot().fpv.cameraForward;"
            f" return f && f[0] * {start[0]} + f[1] * {start[1]} + f[2] * {start[2]}"
            " < Math.cos(0.5); })()",
            30,
            "the drone (and its camera) to yaw about 30 degrees",
        )
    finally:
        page.page.mouse.up()
    time.sleep(0.3)
    second = picture("fpv-moved.png")
    changed = (np.abs(second.astype(int) - first.astype(int)).sum(axis=-1) > 40).mean()
    assert changed >= 0.1, (
        f"the FPV picture hardly changed ({changed:.0%} of pixels) as the drone moved"
    )

    # The mesh came at a bounded rate: one download, then at most one per refresh interval.
    mesh = page.snapshot()["mesh"]
    elapsed = time.time() - t0
    assert 1 <= mesh["downloads"] <= 2 + elapsed / 8.0, (mesh, elapsed)
    assert not page.errors, page.errors


def _png16(values: np.ndarray) -> bytes:
    """A 16-bit greyscale PNG written here, row y with PNG filter type y % 5 (none, sub, up,
    average, Paeth), so that the page's reader meets every filter; split into two IDAT chunks."""
    import struct
    import zlib

    h, w = values.shape
    rows = values.astype(">u2").view(np.uint8).reshape(h, 2 * w).astype(int)
    raw = bytearray()
    for y in range(h):
        cur, up = rows[y], rows[y - 1] if y else np.zeros(2 * w, int)
        left = np.concatenate([[0, 0], cur[:-2]])
        upleft = np.concatenate([[0, 0], up[:-2]])
        f = y % 5
        if f == 0:
            pred = np.zeros_like(cur)
        elif f == 1:
            pred = left
        elif f == 2:
            pred = up
        elif f == 3:
            pred = (left + up) // 2
        else:
            p = left + up - upleft
            pa, pb, pc = np.abs(p - left), np.abs(p - up), np.abs(p - upleft)
            pred = np.where((pa <= pb) & (pa <= pc), left, np.where(pb <= pc, up, upleft))
        raw += bytes([f]) + bytes(((cur - pred) % 256).astype(np.uint8))
    data = zlib.compress(bytes(raw))

    def chunk(kind: bytes, body: bytes) -> bytes:
        crc = zlib.crc32(kind + body)
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", crc)

    header = struct.pack(">IIBBBBB", w, h, 16, 0, 0, 0, 0)
    half = len(data) // 2
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", header)
        + chunk(b"IDAT", data[:half])
        + chunk(b"IDAT", data[half:])
        + chunk(b"IEND", b"")
    )


READERS_JS = """async ([png, cvPng, ply]) => {
  const { decodeDepthPng } = await import('/app/js/formats/depth_png.js');
  const { parseMeshPly } = await import('/app/js/formats/ply.js');
  const bytes = (list) => new Uint8Array(list);
  const a = await decodeDepthPng(bytes(png));
  const b = await decodeDepthPng(bytes(cvPng));
  const m = parseMeshPly(bytes(ply).buffer);
  const { fillDepthHoles } = await import('/app/js/views/occlusion.js');
  const row = new Float32Array([2, 0, 0, 0, 0, 0, 3]);
  const square = new Float32Array([5, 4, 6, 7, 0, 4.5, 9, 8, 0]);
  const filled = [Array.from(fillDepthHoles(row, 7, 1, new Float32Array(7))),
    Array.from(fillDepthHoles(square, 3, 3, new Float32Array(9), 1))];
  const plain = (d) => ({ w: d.width, h: d.height, v: Array.from(d.values) });
  return { a: plain(a), b: plain(b), filled,
    mesh: { p: Array.from(m.positions), c: Array.from(m.colours), i: Array.from(m.indices) } };
}"""


def test_depth_png_mesh_ply_readers_and_hole_filling_in_the_browser(
    live_server, open_page, tmp_path
):
    import open3d as o3d

    rng = np.random.default_rng(3)
    h, w = 24, 33
    depth = (rng.integers(0, 65536, (h, w)) * (rng.random((h, w)) > 0.1)).astype(np.uint16)
    smooth = (5000 * (1 + np.add.outer(np.arange(h), np.arange(w)) / 50)).astype(np.uint16)
    ok, cv_png = cv2.imencode(".png", smooth)
    assert ok
    mesh = o3d.geometry.TriangleMesh.create_box(0.5, 0.3, 0.2).translate((1.0, -2.0, 0.5))
    mesh.compute_vertex_normals()
    colours = rng.random((len(mesh.vertices), 3))
    mesh.vertex_colors = o3d.utility.Vector3dVector(colours)
    o3d.io.write_triangle_mesh(str(tmp_path / "mesh.ply"), mesh, write_ascii=False)
    ply = (tmp_path / "mesh.ply").read_bytes()

    page = open_page(live_server())
    out = page.page.evaluate(READERS_JS, [list(_png16(depth)), list(cv_png.tobytes()), list(ply)])
    assert (out["a"]["w"], out["a"]["h"]) == (w, h)
    assert np.array_equal(np.array(out["a"]["v"]).reshape(h, w), depth)
    assert np.array_equal(np.array(out["b"]["v"]).reshape(h, w), smooth)
    positions = np.array(out["mesh"]["p"]).reshape(-1, 3)
    assert np.allclose(positions, np.asarray(mesh.vertices), atol=1e-6)
    assert np.array_equal(np.array(out["mesh"]["i"]).reshape(-1, 3), np.asarray(mesh.triangles))
    expected = np.round(colours * 255)
    assert np.abs(np.array(out["mesh"]["c"]).reshape(-1, 3) - expected).max() <= 1
    # Occlusion's hole filling: the nearest valid depth within the radius, else still none.
    assert out["filled"][0] == [2, 2, 2, 0, 3, 3, 3]
    assert out["filled"][1] == [5, 4, 6, 7, 4, 4.5, 9, 8, 4.5]  # from the input, not the filled
    assert not page.errors, page.errors


# The AR view alone, on the page: a drone 1 m ahead on the optical axis, seen from above, and a
# depth image that puts a surface at 0.7 m over the left half of the view (no measurement on the
# right), laid out as the view (replay) or transposed with a normDepthBufferFromNormView that
# swaps the axes (as a portrait phone's landscape depth buffer); and the same surface at 1.3 m,
# behind the drone. -> drone-coloured pixels in the left and right halves of the overlay.
OCCLUDER_JS = """async ([surfaceM, transposed]) => {
  const { ARView } = await import('/app/js/views/ar_view.js');
  const box = document.createElement('div');
  box.style.cssText = 'position:fixed;left:0;top:0;width:320px;height:240px;z-index:99';
  document.body.append(box);
  const ar = new ARView(box);
  ar.renderer.setPixelRatio(1);
  ar.setCamera([200, 200, 159.5, 119.5], [320, 240]);
  ar.renderer.setSize(320, 240);
  const identity = [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1];
  ar.showFrame(null, 1, identity);
  // body x -> camera x, body z (up) -> camera -z: the drone shows its top to the camera
  const T_world_drone = [1, 0, 0, 0, 0, -1, 0, 0, 0, 0, -1, 1, 0, 0, 0, 1];
  ar.setDroneState({ mode: 'hover', T_world_drone });
  const [W, H] = [160, 120];
  const depth = new Float32Array(W * H);
  let matrix = null;
  for (let y = 0; y < H; y++) for (let x = 0; x < W; x++) {
    const u = (x + 0.5) / W;
    if (!transposed) depth[y * W + x] = u < 0.5 ? surfaceM : 0;
  }
  if (transposed) { // a buffer H wide, W high: its (column, row) is the view's (v, u)
    for (let by = 0; by < W; by++) {
      for (let bx = 0; bx < H; bx++) depth[by * H + bx] = (by + 0.5) / W < 0.5 ? surfaceM : 0;
    }
    matrix = [0, 1, 0, 0, 1, 0, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1];
  }
  ar.occlusion.setDepth(depth, transposed ? H : W, transposed ? W : H, 1, matrix);
  ar.render(0);
  const canvas = document.createElement('canvas');
  canvas.width = 320; canvas.height = 240;
  const ctx = canvas.getContext('2d');
  ctx.drawImage(ar.renderer.domElement, 0, 0, 320, 240);
  const px = ctx.getImageData(0, 0, 320, 240).data;
  let left = 0, right = 0;
  for (let i = 0; i < px.length; i += 4) {
    const [r, g, b] = [px[i], px[i + 1], px[i + 2]];
    if (!(r > 130 && b > 95 && g < 90 && r - g > 90 && b - g > 60)) continue;
    // Columns next to the edge are left out: hole filling carries the surface up to 2 depth
    // pixels (4 view pixels here) into the unmeasured half.
    const column = (i / 4) % 320;
    if (column < 152) left++; else if (column >= 168) right++;
  }
  const source = ar.lastDraw.occlusion;
  ar.renderer.dispose();
  box.remove();
  return { left, right, source };
}"""


def test_the_occluder_hides_what_is_behind_the_depth_in_either_layout(live_server, open_page):
    page = open_page(live_server())
    for transposed in (False, True):
        near = page.page.evaluate(OCCLUDER_JS, [0.7, transposed])
        far = page.page.evaluate(OCCLUDER_JS, [1.3, transposed])
        assert near["source"] == far["source"] == "depth"
        # Behind a surface at 0.7 m the left half of the drone is gone, the right half (no depth
        # measured there) shows; a surface at 1.3 m hides nothing of a drone at 1 m.
        assert far["left"] >= 30 and far["right"] >= 30, (transposed, far)
        assert near["left"] <= 0.05 * far["left"], (transposed, near, far)
        assert near["right"] >= 0.8 * far["right"], (transposed, near, far)
    assert not page.errors, page.errors
