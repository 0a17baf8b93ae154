"""The emulated WebXR AR device of the browser tests (tests/support/webxr/emulated_ar_device.js),
fed from a recorded RGB-D sequence as a phone with ARCore would see the same room.

A device profile says what the phone gives the page: its view (the screen, in pixels), how the
sensor's image is turned into it (portrait, landscape, reverse landscape; a sensor mounted at 90
or 270 degrees), the camera image Chrome gives (ARCore's 1920x1080 image turned and cropped to
the view's aspect), the depth buffer's size and formats; and what today's Chrome does: the WebXR
Layers API (Chrome 147+), depth only with some camera frames and none until the phone moves,
ARCore losing tracking and coming back with its poses jumped. The sequence's camera is the phone's
sensor: its images are turned and cropped to the view's aspect, as ARCore crops the camera to
the screen; depth is cropped to the depth buffer's aspect (ARCore's depth covers a 16:9 or 4:3
crop of the sensor) and subsampled to the buffer's size, in the sensor's landscape orientation.
normDepthBufferFromNormView maps one onto the other. Viewer poses are the ground truth with a
phone's visual-inertial drift and noise (server.evaluation.device_poses), in a gravity-aligned
space whose up is the first frame's camera up (the sequences here are filmed upright).

``prepare`` writes the frames as files and returns the device's configuration (for the page) and
the truth (for the test); ``FileServer`` serves the files on loopback; ``install`` puts the
device into a browser context before its first page loads.
"""

from __future__ import annotations

import functools
import http.server
import json
import threading
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from server.datasets.base import RGBDDataset
from server.evaluation.device_poses import DeviceDrift, device_world, drifting_device_poses
from server.geometry import Intrinsics

EMULATOR_JS = Path(__file__).parent / "webxr" / "emulated_ar_device.js"
GL_FROM_CV = np.diag([1.0, -1.0, -1.0, 1.0])  # OpenCV camera axes <-> WebXR/GL (y up, z back)
NEAR_M, FAR_M = 0.1, 1000.0  # Chrome's default depthNear / depthFar


@dataclass(frozen=True)
class DeviceProfile:
    """What an AR phone or tablet gives a page."""

    name: str
    view_size: tuple[int, int]  # the XR view (the screen's XR framebuffer), (width, height) px
    # Degrees the sensor's image is turned clockwise into the view: 0 landscape, 90 portrait
    # (a back camera mounted at 90 degrees, most phones), 180 reverse landscape (the phone turned
    # the other way), 270 portrait with a sensor mounted at 270 degrees (e.g. Nexus 5X).
    turn: int
    depth_size: tuple[int, int]  # ARCore's depth buffer, sensor orientation (landscape), px
    # Chrome on ARCore gives depth as luminance-alpha (newer: unsigned-short), uint16 with
    # rawValueToMeters 0.001, never float32; the first of the page's preferences it has.
    depth_formats: tuple[str, ...] = ("luminance-alpha", "unsigned-short")
    # ARCore's camera image (landscape, px): Chrome's XRCamera is this image turned into the
    # view and cropped to the view's aspect (a 1920x1080 image gives 864x1920 on a 20:9
    # portrait screen), not the view's own pixel size.
    sensor_size: tuple[int, int] = (1920, 1080)
    fps: float = 30.0  # camera rate
    display_hz: float = 30.0  # XR frames per second
    empty_depth_s: float = 1.0  # depth from motion: all zero for this long after the start
    missing_depth_every: int = 37  # every n-th camera frame starts a run without depth information
    missing_camera_every: int = 53  # ... a run without a camera image (0: never)
    # Frames in each such run (ARCore's depth can miss a few in a row). A page that samples
    # every k-th camera frame meets a run of 2 with a chance of about 2/k, and passes all 27
    # runs of a 600-frame recording with (1 - 2/k)^27: 2e-5 at k = 6, a loaded machine's rate
    # (96 of 600 sampled), where single missing frames were once all passed. Longer runs cost
    # the emulated phone more of its frames (3: 41-49 without depth against 7 at 1).
    missing_run: int = 2
    features: tuple[str, ...] = ("depth-sensing", "camera-access")
    camera_denied: bool = False  # the user refused the camera permission: no camera-access
    # The camera image and XR framebuffer at this fraction of the view's pixels: software WebGL
    # on two cores cannot fill 1080x2400 at 30 Hz beside a tracking server. The projection
    # matrix, aspect ratios and depth mapping are the full-size view's; only pixels are fewer.
    pixel_scale: float = 0.25
    # Chrome 147+: XRWebGLBinding.prototype.createProjectionLayer exists (three.js then renders
    # into a projection layer, baseLayer null) and getCameraImage without a baseLayer crashes.
    layers_api: bool = False
    # Depth as Chrome gives it: only on XR frames with a new ARCore depth image, here every n-th
    # new camera frame (0: on every XR frame, as before); null, not zeros, until the phone has
    # moved this far (m) from where it started (0: off); or never (a phone that gives none).
    depth_every: int = 0
    depth_after_move_m: float = 0.0
    depth_never: bool = False
    # ARCore stops tracking for (start s, length s): null viewer poses; when it tracks again its
    # poses have jumped by pose_jump_m (relocalised into a shifted local space).
    pose_lost: tuple[float, float] | None = None
    pose_jump_m: tuple[float, float, float] = (0.12, 0.0, 0.16)  # 20 cm, in the local space
    max_frames: int | None = None  # play only the recording's first frames


# Chrome 147+ on a phone whose depth comes as Chrome gives it: null until the phone has moved
# 5 cm (7scenes_a's camera does in its first second), then with every 2nd or 3rd camera frame.
# No scripted runs without depth: every null is Chrome's own.
_TODAY = dict(layers_api=True, empty_depth_s=0.0, missing_depth_every=0, depth_after_move_m=0.05)
PROFILES = {
    p.name: p
    for p in (
        DeviceProfile("phone-portrait", (1080, 2400), 90, (160, 90)),
        DeviceProfile("phone-landscape", (2400, 1080), 0, (160, 90)),
        # A tablet whose camera is mounted at 270 degrees: its view turns the sensor's image the
        # other way, and normDepthBufferFromNormView with it.
        DeviceProfile("tablet-4x3-sensor-270", (1536, 2048), 270, (160, 120)),
        # Reverse landscape: the phone turned the other way round, its view the sensor's image
        # upside down.
        DeviceProfile(
            "chrome147-reverse-landscape-depth-every-2",
            (2400, 1080),
            180,
            (160, 90),
            depth_every=2,
            **_TODAY,
        ),
        # ARCore loses tracking for 1 s, 9 s in (the camera moves ~0.2 m meanwhile), and its
        # poses come back 20 cm off. A 4:3 view: through the 20:9 portrait view's narrow crop
        # the server's flow did not bridge the gap (1 s and 1.5 s, one run each), and the frames
        # until it found the map again were placed roughly (a map segment): ATE 12.7 and 17.9 cm
        # (docs/LIVE_AR.md).
        DeviceProfile(
            "chrome147-depth-every-3-vio-loss",
            (1536, 2048),
            90,
            (160, 120),
            depth_every=3,
            pose_lost=(9.0, 1.0),
            **_TODAY,
        ),
    )
}
# A phone whose ARCore never gives depth (the user never moves it, or a scene it cannot
# measure): the page must say so. 5 s of recording; then the phone is held still.
NEVER_DEPTH = DeviceProfile(
    "chrome147-never-depth",
    (1080, 2400),
    90,
    (160, 90),
    depth_never=True,
    max_frames=150,
    **_TODAY,
)

# Phones that cannot stream live AR, for the page's start-up: the user refused the camera
# permission (camera-access is not granted), or ARCore has no Depth API on this model.
CAMERA_DENIED = DeviceProfile("camera-denied", (1080, 2400), 90, (160, 90), camera_denied=True)
NO_DEPTH_SUPPORT = DeviceProfile(
    "no-depth-support", (1080, 2400), 90, (160, 90), features=("camera-access",)
)


def _centre_crop(size: tuple[float, float], aspect: float) -> tuple[float, float, float, float]:
    """(x0, y0, w, h): the largest centred crop of a w x h image with width/height = aspect."""
    w, h = size
    if w / h > aspect:
        cw, ch = h * aspect, h
    else:
        cw, ch = w, w / aspect
    return (w - cw) / 2, (h - ch) / 2, cw, ch


@dataclass
class PreparedDevice:
    """The device's configuration (JSON for the page, less ``base``) and the truth."""

    config: dict
    T_world_view: np.ndarray  # (N, 4, 4) true camera poses of the view, OpenCV axes, metres
    K_view: Intrinsics  # the view's camera at the XR framebuffer's size (view_size x pixel_scale)
    stamps: np.ndarray  # (N,) the recording's timestamps, seconds
    sensor_crop: tuple[float, float, float, float]  # view's crop of the (turned) sensor image
    folder: Path  # where the recording's files are

    def camera_image(self, index: int) -> np.ndarray:
        """Recording frame ``index`` as the device's camera shows it, RGB at the XR
        framebuffer's size (the tests' pictures put the page's overlay over it)."""
        offsets = self.config["colourOffsets"]
        with open(self.folder / "colour.bin", "rb") as f:
            f.seek(offsets[index])
            jpeg = f.read(offsets[index + 1] - offsets[index])
        bgr = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
        size = (self.K_view.width, self.K_view.height)
        return cv2.resize(bgr, size, interpolation=cv2.INTER_AREA)[..., ::-1]


def _quarter_turns(size: tuple[int, int], turn: int) -> tuple[np.ndarray, np.ndarray, tuple]:
    """An image of ``size`` (w, h) turned ``turn`` degrees clockwise (a multiple of 90): (the
    affine map of pixel edge coordinates, turned from unturned, 3x3; R_unturned_turned, the
    rotation of camera axes; the turned size)."""
    assert turn % 90 == 0, turn
    A, R = np.eye(3), np.eye(3)
    w, h = size
    for _ in range(turn // 90 % 4):
        # One quarter turn clockwise: x' = h - y, y' = x; camera X' = -Y, Y' = X.
        A = np.array([[0.0, -1.0, h], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]) @ A
        R = R @ np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
        w, h = h, w
    return A, R, (w, h)


def _view_of_sensor(K: Intrinsics, profile: DeviceProfile):
    """The sensor -> view mapping: (view intrinsics, crop of the turned sensor image,
    R_sensor_view, the affine map from view pixels (edge coordinates: 0..W) to sensor pixels,
    as a 3x3)."""
    # Edge coordinates (pixel centres at +0.5) make turns, crops and scales plain affine maps.
    K_edge = np.array([[K.fx, 0.0, K.cx + 0.5], [0.0, K.fy, K.cy + 0.5], [0.0, 0.0, 1.0]])
    turned_from_sensor, R_sensor_view, turned = _quarter_turns((K.width, K.height), profile.turn)
    W, H = profile.view_size
    crop = _centre_crop(turned, W / H)
    s = W / crop[2]
    view_from_turned = np.array([[s, 0, -crop[0] * s], [0, s, -crop[1] * s], [0, 0, 1.0]])
    # A point seen by the sensor: sensor px = K X_s, X_s = R_sensor_view X_v.
    Kv = view_from_turned @ turned_from_sensor @ K_edge @ R_sensor_view
    assert abs(Kv[0, 1]) < 1e-9 and abs(Kv[1, 0]) < 1e-9, Kv
    K_view = Intrinsics(Kv[0, 0], Kv[1, 1], Kv[0, 2] - 0.5, Kv[1, 2] - 0.5, W, H)
    sensor_from_view = np.linalg.inv(view_from_turned @ turned_from_sensor)
    return K_view, crop, R_sensor_view, sensor_from_view


def camera_size(profile: DeviceProfile) -> tuple[int, int]:
    """Chrome's XRCamera size (px): ARCore's camera image turned into the view and cropped to
    the view's aspect (e.g. 864x1920 from 1920x1080 on a 20:9 portrait screen)."""
    *_, turned = _quarter_turns(profile.sensor_size, profile.turn)
    _, _, w, h = _centre_crop(turned, profile.view_size[0] / profile.view_size[1])
    return round(w), round(h)


def projection_matrix(K: Intrinsics) -> list[float]:
    """The view's WebXR projection matrix (column-major, OpenGL clip space) for intrinsics K
    (pixel centres at integers), as the page's intrinsicsFromProjection inverts it."""
    W, H = K.width, K.height
    p = np.zeros(16)
    p[0] = 2 * K.fx / W
    p[5] = 2 * K.fy / H
    p[8] = 1 - (2 * K.cx + 1) / W
    p[9] = (2 * K.cy + 1) / H - 1
    p[10] = -(FAR_M + NEAR_M) / (FAR_M - NEAR_M)
    p[11] = -1
    p[14] = -2 * FAR_M * NEAR_M / (FAR_M - NEAR_M)
    return p.tolist()


def gravity_aligned(T_world_camera: np.ndarray) -> np.ndarray:
    """T_local_world: a y-up space at the first camera, up = that camera's up (-y in OpenCV
    axes), -z its optical axis made level; as ARCore's "local" space starts."""
    R0, p0 = T_world_camera[0, :3, :3], T_world_camera[0, :3, 3]
    up = -R0[:, 1]
    back = -R0[:, 2] + 0.0
    back -= up * (back @ up)
    back /= np.linalg.norm(back)
    x = np.cross(up, back)
    T_world_local = np.eye(4)
    T_world_local[:3, :3] = np.column_stack([x, up, back])
    T_world_local[:3, 3] = p0
    return np.linalg.inv(T_world_local)


def prepare(
    dataset: RGBDDataset,
    profile: DeviceProfile,
    out: Path,
    max_frames: int | None = None,
    drift: DeviceDrift | None = None,
) -> PreparedDevice:
    """Write the sequence's frames as the device shows them into ``out``: colour.bin (the JPEGs
    of the sensor's crop end to end, offsets in the configuration) and depth.bin (each frame's
    depth buffer, raw little-endian values); return the device's configuration and the truth."""
    assert dataset.ground_truth is not None, "the emulated device needs ground-truth poses"
    # depth.bin holds one encoding, whichever of the formats the page picks.
    assert profile.depth_formats == ("float32",) or "float32" not in profile.depth_formats
    max_frames = max_frames if max_frames is not None else profile.max_frames
    n = len(dataset) if max_frames is None else min(max_frames, len(dataset))
    K = dataset.intrinsics
    K_view, crop, R_sensor_view, sensor_from_view = _view_of_sensor(K, profile)
    W, H = profile.view_size

    # The depth buffer covers a centred crop of the sensor with its own aspect.
    dw, dh = profile.depth_size
    dcrop = _centre_crop((K.width, K.height), dw / dh)
    # normDepthBufferFromNormView: view (0..1) -> view px -> sensor px -> buffer (0..1).
    view_px = np.diag([W, H, 1.0])
    buffer_norm = np.array(
        [
            [1 / dcrop[2], 0, -dcrop[0] / dcrop[2]],
            [0, 1 / dcrop[3], -dcrop[1] / dcrop[3]],
            [0, 0, 1],
        ]
    )
    A = buffer_norm @ sensor_from_view @ view_px
    norm = np.eye(4)
    norm[:2, :2], norm[:2, 3] = A[:2, :2], A[:2, 2]

    out.mkdir(parents=True, exist_ok=True)
    offsets = [0]
    x0, y0, cw, ch = (int(round(v)) for v in crop)
    dx0, dy0, dcw, dch = (int(round(v)) for v in dcrop)
    jpegs: list[bytes] = []
    depths: list[bytes] = []
    for i in range(n):
        frame = dataset[i]
        colour = frame.colour
        if profile.turn % 360:
            colour = cv2.rotate(colour, _CV_TURNS[profile.turn % 360])
        colour = np.ascontiguousarray(colour[y0 : y0 + ch, x0 : x0 + cw])
        ok, jpeg = cv2.imencode(".jpg", colour[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 92])
        assert ok
        jpegs.append(jpeg.tobytes())
        offsets.append(offsets[-1] + len(jpegs[-1]))
        depth = frame.depth[dy0 : dy0 + dch, dx0 : dx0 + dcw]
        depth = cv2.resize(depth, (dw, dh), interpolation=cv2.INTER_NEAREST)
        if profile.depth_formats[0] == "float32":
            raw = depth.astype("<f4")
        else:
            raw = np.clip(np.round(depth * 1000.0), 0, 65535).astype("<u2")
        depths.append(raw.tobytes())
    (out / "colour.bin").write_bytes(b"".join(jpegs))
    (out / "depth.bin").write_bytes(b"".join(depths))

    gt = dataset.ground_truth
    stamps = dataset.timestamps[:n]
    T_world_sensor = np.stack([gt.poses[_nearest(gt.timestamps, t)] for t in stamps])
    S = np.eye(4)
    S[:3, :3] = R_sensor_view
    T_world_view = T_world_sensor @ S
    # The phone's odometry: drift and noise in a gravity-aligned frame (drifting_device_poses
    # yaws about y), then that frame's origin at the first camera, as ARCore's local space.
    T_local_world = gravity_aligned(T_world_sensor)
    T_local_view = T_local_world @ T_world_view
    drift = drift or DeviceDrift()
    T_vio = np.linalg.inv(device_world(drift.seed)) @ drifting_device_poses(
        T_local_view, stamps, drift
    )
    pose_lost: list[int] = []
    if profile.pose_lost is not None:
        # ARCore is not tracking for these frames; afterwards its local space has moved.
        start, length = profile.pose_lost
        t = stamps - stamps[0]
        pose_lost = np.flatnonzero((t >= start) & (t < start + length)).tolist()
        after = t >= start + length
        T_vio[after, :3, 3] += np.asarray(profile.pose_jump_m)
    poses_gl = [(T @ GL_FROM_CV).T.reshape(-1).tolist() for T in T_vio]  # column-major

    pw, ph = (round(v * profile.pixel_scale) for v in profile.view_size)
    config = {
        "profile": profile.name,
        "frames": n,
        "colourOffsets": offsets,
        "fps": profile.fps,
        "displayHz": profile.display_hz,
        "viewSize": [pw, ph],
        "cameraSize": [round(v * profile.pixel_scale) for v in camera_size(profile)],
        "projection": projection_matrix(K_view),
        "poses": poses_gl,
        "depthSize": [dw, dh],
        "depthFormats": list(profile.depth_formats),
        "normDepthBufferFromNormView": norm.T.reshape(-1).tolist(),
        "emptyDepthS": profile.empty_depth_s,
        "missingDepth": _every(n, profile.missing_depth_every, 5, profile.missing_run),
        "missingCamera": _every(n, profile.missing_camera_every, 11, profile.missing_run),
        "features": list(profile.features),
        "cameraDenied": profile.camera_denied,
        "layersApi": profile.layers_api,
        "depthEvery": profile.depth_every,
        "depthAfterMoveM": profile.depth_after_move_m,
        "depthNever": profile.depth_never,
        "poseLost": pose_lost,
    }
    K_pixels = Intrinsics(
        (K_view.fx * pw / W),
        (K_view.fy * ph / H),
        (K_view.cx + 0.5) * pw / W - 0.5,
        (K_view.cy + 0.5) * ph / H - 0.5,
        pw,
        ph,
    )
    return PreparedDevice(config, T_world_view, K_pixels, stamps, crop, out)


_CV_TURNS = {
    90: cv2.ROTATE_90_CLOCKWISE,
    180: cv2.ROTATE_180,
    270: cv2.ROTATE_90_COUNTERCLOCKWISE,
}


def _every(n: int, every: int, start: int, run: int) -> list[int]:
    """Frame indices below n in runs of ``run``, one starting every ``every`` frames."""
    if every <= 0:
        return []
    return [i + k for i in range(start, n, every) for k in range(run) if i + k < n]


def _nearest(stamps: np.ndarray, t: float) -> int:
    return int(np.argmin(np.abs(stamps - t)))


class FileServer:
    """A folder served over HTTP on 127.0.0.1 with CORS (the page's origin is the app server's),
    in a thread: the device's recording."""

    def __init__(self, root: Path) -> None:
        handler = functools.partial(_CorsHandler, directory=str(root))
        self.httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}"
        self.thread = threading.Thread(target=self.httpd.serve_forever, daemon=True)
        self.thread.start()

    def close(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()


class _CorsHandler(http.server.SimpleHTTPRequestHandler):
    def end_headers(self) -> None:
        self.send_header("Access-Control-Allow-Origin", "*")
        self.send_header("Cache-Control", "no-store")
        super().end_headers()

    def log_message(self, *args) -> None:  # quiet: hundreds of frames
        pass


def install(context, config: dict, base_url: str) -> None:
    """Give a Playwright browser context the emulated device (before any page loads)."""
    context.add_init_script(
        script=f"window.__xrDeviceConfig = {json.dumps({**config, 'base': base_url})};"
    )
    context.add_init_script(path=str(EMULATOR_JS))
