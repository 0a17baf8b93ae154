"""A self-made demo RGB-D sequence: a procedurally textured room, ray cast with exact ground truth.

The product may not ship a real dataset, so it generates one on first use and caches it. The folder
has the TUM RGB-D layout of ``shared/data/synthetic_room0``, so the TUM loader reads it unchanged:
rgb/*.jpg (JPEG quality 95), depth/*.png (uint16, metres * 5000, 0 = no measurement), rgb.txt,
depth.txt, associations.txt, groundtruth.txt (T_world_camera), intrinsics.json and README.txt.

World frame: metres, z up, origin on the floor at the centre of the room. Camera frame: x right,
y down, z forward. All randomness comes from seeded ``numpy.random.Generator`` objects, so one spec
always gives the same ground truth and byte-identical depth images.
"""

from __future__ import annotations

import functools
import hashlib
import json
import logging
import os
import shutil
import time
from dataclasses import asdict, astuple, dataclass
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
from tqdm import tqdm

from server.errors import ConfigError
from server.geometry import Intrinsics, quaternion_from_pose

logger = logging.getLogger(__name__)

GENERATOR_VERSION = 1  # bump whenever the output changes, so that stale caches are not reused
DEPTH_SCALE = 5000.0  # depth PNG units per metre, as in TUM RGB-D
START_TIME = 1700000000.0  # timestamp of frame 0, seconds
ROOM = (6.0, 5.0, 2.8)  # inner extent of the room along x, y, z, metres
LIGHT = np.array([0.3, -0.2, 2.5], dtype=np.float32)  # point light, world frame, metres
# Surface patterns: (mosaic cell size in metres, share of random colour per large cell).
PATTERNS = {
    "wall": (0.06, 0.35),
    "ceiling": (0.08, 0.3),
    "floor": (0.05, 0.3),
    "wood": (0.035, 0.25),
    "box": (0.05, 0.5),
    "poster": (0.03, 1.0),
}


@dataclass(frozen=True)
class DemoSpec:
    """What to generate: frame count, image size (pixels), frame rate (Hz), pinhole intrinsics
    (pixels), random seed, and whether to add Kinect-like depth and colour noise."""

    frames: int = 150
    width: int = 640
    height: int = 480
    fps: float = 30.0
    fx: float = 525.0
    fy: float = 525.0
    cx: float = 319.5
    cy: float = 239.5
    seed: int = 7
    noise: bool = True

    def __post_init__(self) -> None:
        if self.frames < 1 or not self.fps > 0:
            raise ConfigError(f"demo needs frames >= 1 and fps > 0, got {self.frames}, {self.fps}")
        self.intrinsics  # noqa: B018 -- validates focal lengths and image size

    @property
    def intrinsics(self) -> Intrinsics:
        return Intrinsics(self.fx, self.fy, self.cx, self.cy, self.width, self.height)

    def key(self) -> str:
        """Short hash of every field and the generator version, for the cache folder name."""
        return hashlib.sha256(repr((GENERATOR_VERSION, *astuple(self))).encode()).hexdigest()[:12]


def _room_boxes(rng: np.random.Generator) -> list[tuple[tuple, tuple, str]]:
    """Axis-aligned boxes (min corner, max corner, pattern), metres, world frame. The layout is
    fixed (it leaves the camera's space free); only the book sizes depend on the seed."""
    X, Y, Z, w = ROOM[0] / 2, ROOM[1] / 2, ROOM[2], 0.2
    boxes = [  # floor, ceiling and four walls, as thick slabs outside the room
        ((-X - w, -Y - w, -w), (X + w, Y + w, 0.0), "floor"),
        ((-X - w, -Y - w, Z), (X + w, Y + w, Z + w), "ceiling"),
        ((-X - w, -Y, 0.0), (-X, Y, Z), "wall"),
        ((X, -Y, 0.0), (X + w, Y, Z), "wall"),
        ((-X - w, -Y - w, 0.0), (X + w, -Y, Z), "wall"),
        ((-X - w, Y, 0.0), (X + w, Y + w, Z), "wall"),
    ]
    for x0, y0, x1, y1 in ((0.6, -2.3, 2.0, -1.5), (-2.6, 0.2, -1.6, 1.4)):  # two tables
        boxes.append(((x0, y0, 0.72), (x1, y1, 0.77), "wood"))
        for lx, ly in ((x0, y0), (x1 - 0.06, y0), (x0, y1 - 0.06), (x1 - 0.06, y1 - 0.06)):
            boxes.append(((lx, ly, 0.0), (lx + 0.06, ly + 0.06, 0.72), "wood"))
    boxes += [  # boxes on the floor and on a table, and a pillar
        ((-0.5, 1.6, 0.0), (0.1, 2.2, 0.5), "box"),
        ((2.2, 0.8, 0.0), (2.8, 1.4, 0.4), "box"),
        ((1.0, -2.1, 0.77), (1.4, -1.7, 1.07), "box"),
        ((1.8, 1.2, 0.0), (2.1, 1.5, Z), "wall"),
    ]
    x0, x1, y0, y1 = -2.4, -1.0, -Y, -Y + 0.35  # shelf against the -y wall, with books
    boxes += [
        ((x0, y0, 0.0), (x0 + 0.03, y1, 2.0), "wood"),
        ((x1 - 0.03, y0, 0.0), (x1, y1, 2.0), "wood"),
    ]
    for z in (0.05, 0.5, 1.0, 1.5, 1.97):
        boxes.append(((x0 + 0.03, y0, z), (x1 - 0.03, y1, z + 0.03), "wood"))
        for k in range(3 if z < 1.9 else 0):
            bw, bh, bd = rng.uniform(0.12, 0.3), rng.uniform(0.15, 0.4), rng.uniform(0.15, 0.3)
            bx = x0 + 0.08 + 0.42 * k
            boxes.append(((bx, y0, z + 0.03), (bx + bw, y0 + bd, z + 0.03 + bh), "box"))
    boxes += [  # posters, 1 cm in front of the walls
        ((X - 0.01, -0.8, 1.0), (X, 0.4, 1.8), "poster"),
        ((-X, -1.5, 1.1), (-X + 0.01, -0.5, 1.9), "poster"),
        ((-1.0, Y - 0.01, 1.0), (0.4, Y, 2.0), "poster"),
        ((0.2, -Y, 1.2), (1.4, -Y + 0.01, 2.0), "poster"),
    ]
    return boxes


def build_scene(spec: DemoSpec) -> tuple[o3d.t.geometry.RaycastingScene, dict[str, np.ndarray]]:
    """The room as a ray-casting scene, and per-geometry-id materials: ``colour`` (G, 3) base RGB
    in [0, 1], ``cell`` (G,) mosaic cell size in metres, ``mix`` (G,) share of random colour."""
    rng = np.random.default_rng([spec.seed, 1])
    scene = o3d.t.geometry.RaycastingScene()
    colour, cell, mix = [], [], []
    for lo, hi, pattern in _room_boxes(rng):
        mesh = o3d.geometry.TriangleMesh.create_box(*np.subtract(hi, lo))
        mesh.translate(lo)  # in place (it returns the mesh typed as a plain Geometry3D)
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
        colour.append(rng.uniform(0.35, 0.95, 3))
        cell.append(PATTERNS[pattern][0])
        mix.append(PATTERNS[pattern][1])
    materials = {"colour": np.array(colour), "cell": np.array(cell), "mix": np.array(mix)}
    return scene, {k: v.astype(np.float32) for k, v in materials.items()}


def camera_poses(spec: DemoSpec) -> np.ndarray:
    """T_world_camera (N, 4, 4), metres, of a smooth hand-held-like path in the middle of the room.

    Position and yaw/pitch/roll are sums of sinusoids with seeded phases and slightly seeded
    frequencies; the amplitudes keep the camera in |x| < 1.05, |y| < 0.85, 1.3 < z < 1.7 m, which
    is at least 0.5 m from every surface, looking about 14 degrees down while turning.
    """
    rng = np.random.default_rng([spec.seed, 2])
    t = np.arange(spec.frames) / spec.fps

    def waves(amplitudes: list[float], hz: list[float]) -> np.ndarray:
        phase = rng.uniform(0.0, 2 * np.pi, (len(hz), 1))
        freq = np.array(hz)[:, None] * rng.uniform(0.9, 1.1, (len(hz), 1))
        return (np.array(amplitudes)[:, None] * np.sin(2 * np.pi * freq * t + phase)).sum(axis=0)

    x = waves([0.7, 0.25, 0.08, 0.01], [0.075, 0.2, 0.5, 1.7])
    y = waves([0.55, 0.2, 0.08, 0.01], [0.09, 0.22, 0.55, 1.9])
    z = 1.5 + waves([0.12, 0.06, 0.01], [0.1, 0.3, 2.1])
    turn = rng.choice([-1.0, 1.0]) * 0.45  # slow steady turn, rad/s
    yaw = rng.uniform(0, 2 * np.pi) + turn * t + waves([0.3, 0.06, 0.004], [0.12, 0.4, 2.3])
    pitch = -0.25 + waves([0.12, 0.05, 0.004], [0.1, 0.35, 2.5])
    roll = waves([0.06, 0.02], [0.15, 0.5])

    forward = np.stack([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)], 1)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right, axis=1, keepdims=True)
    down = np.cross(forward, right)
    c, s = np.cos(roll)[:, None], np.sin(roll)[:, None]  # roll about the optical axis
    poses = np.tile(np.eye(4), (spec.frames, 1, 1))
    poses[:, :3, 0] = c * right + s * down
    poses[:, :3, 1] = c * down - s * right
    poses[:, :3, 2] = forward
    poses[:, :3, 3] = np.stack([x, y, z], 1)
    return poses


def _hash(ix: np.ndarray, iy: np.ndarray, gid: np.ndarray, salt: int) -> np.ndarray:
    """Deterministic pseudo-random uint32 per uint32 lattice point and geometry id (products
    wrap around, as the hash wants)."""
    h = (ix * 0x8DA6B343) ^ (iy * 0xD8163841) ^ (gid * 0xCB1AB31F + np.uint32(salt))
    h = (h ^ (h >> 15)) * 0x2C1B3C6D
    h = (h ^ (h >> 12)) * 0x297A2D39
    return h ^ (h >> 15)


def _unit(h: np.ndarray) -> np.ndarray:
    """The top 24 bits of a hash as float32 in [0, 1)."""
    return (h >> 8).astype(np.float32) * np.float32(2.0**-24)


def _cells(u: np.ndarray, v: np.ndarray, size, gid: np.ndarray, salt: int) -> np.ndarray:
    """Random uint32 per square cell of ``size`` metres: sharp-edged mosaics full of corners."""
    return _hash((u / size).astype(np.uint32), (v / size).astype(np.uint32), gid, salt)


def _value_noise(u: np.ndarray, v: np.ndarray, size: float, gid: np.ndarray, salt: int):
    """Smooth value noise in [0, 1] with features of about ``size`` metres."""
    x, y = u / size, v / size
    ix, iy = x.astype(np.uint32), y.astype(np.uint32)  # u, v > 0, so this is floor
    fx, fy = x - np.floor(x), y - np.floor(y)
    a, b = _unit(_hash(ix, iy, gid, salt)), _unit(_hash(ix + 1, iy, gid, salt))
    c, d = _unit(_hash(ix, iy + 1, gid, salt)), _unit(_hash(ix + 1, iy + 1, gid, salt))
    fx, fy = fx * fx * (3 - 2 * fx), fy * fy * (3 - 2 * fy)
    return a + (b - a) * fx + (c - a) * fy + (a - b - c + d) * fx * fy


def surface_colour(p: np.ndarray, n: np.ndarray, gid: np.ndarray, materials: dict, seed: int):
    """Shaded RGB in [0, 1] (N, 3) of hit points ``p`` (N, 3) with unit normals ``n`` (N, 3)
    facing the camera, both world frame: a procedural albedo times Lambertian shading."""
    a = np.abs(n)  # surfaces are axis-aligned: texture them in the two in-plane axes
    axis = np.where(a[:, 2] > np.maximum(a[:, 0], a[:, 1]), 2, a[:, 1] > a[:, 0]).astype(np.uint32)
    u = np.where(axis == 0, p[:, 1], p[:, 0]) + np.float32(50.0)  # + 50 m keeps u, v > 0
    v = np.where(axis == 2, p[:, 1], p[:, 2]) + np.float32(50.0)
    face = gid * 3 + axis  # a different pattern on each orientation of each object
    cell, mix = materials["cell"][gid], materials["mix"][gid, None]
    base = np.take(materials["colour"], gid, axis=0)
    salt = seed * 7919
    # large cells of random colour, a fine mosaic of random brightness, and smooth stains
    big = _cells(u, v, 5 * cell, face, salt)[:, None] >> np.array([0, 8, 16], np.uint32)
    random_rgb = (big & 255).astype(np.float32) * np.float32(1 / 255)
    albedo = (1 - mix) * base + mix * random_rgb
    albedo *= (0.65 + 0.6 * _unit(_cells(u + 0.37 * cell, v, cell, face, salt + 3)))[:, None]
    albedo *= (0.75 + 0.4 * _value_noise(u, v, 0.2, face, salt + 4))[:, None]
    tile_u, tile_v = u - np.floor(u * 2) / 2, v - np.floor(v * 2) / 2  # position in 0.5 m tiles
    grout = (np.minimum(tile_u, tile_v) < 0.012) & (axis == 2) & (p[:, 2] < 0.01)
    albedo[grout] = 0.15  # dark lines between the floor tiles
    to_light = LIGHT - p
    dist = np.sqrt(np.einsum("ij,ij->i", to_light, to_light))
    lambert = np.clip(np.einsum("ij,ij->i", n, to_light) / dist, 0.0, 1.0)
    shade = 0.35 + 0.8 * lambert / (1.0 + 0.04 * dist**2)
    return np.clip(albedo * shade[:, None], 0.0, 1.0)


@functools.lru_cache(maxsize=4)
def _camera_rays(spec: DemoSpec) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per pixel centre (H * W,): the camera-frame ray (x, y, 1) as x and y, and 1 / its length."""
    v, u = np.mgrid[0 : spec.height, 0 : spec.width].astype(np.float32)
    x, y = ((u - spec.cx) / spec.fx).ravel(), ((v - spec.cy) / spec.fy).ravel()
    return x, y, 1.0 / np.sqrt(x * x + y * y + 1.0)


def render_frame(scene, materials: dict, T_world_camera: np.ndarray, spec: DemoSpec, index: int):
    """Ray cast one frame: (colour (H, W, 3) uint8 RGB, depth (H, W) float32 metres along the
    optical axis, 0 = no measurement). Noise, when on, uses a generator seeded by (seed, index)."""
    x, y, inv_length = _camera_rays(spec)
    R, origin = T_world_camera[:3, :3].astype(np.float32), T_world_camera[:3, 3].astype(np.float32)
    rays = np.empty((x.size, 6), np.float32)  # origin, direction; columnwise: faster than matmul
    rays[:, :3] = origin
    for i in range(3):
        rays[:, 3 + i] = R[i, 0] * x + R[i, 1] * y + R[i, 2]
    dirs = rays[:, 3:]
    hit = scene.cast_rays(o3d.core.Tensor.from_numpy(rays))  # shares rays' memory, read only
    z = hit["t_hit"].numpy()  # directions have unit z in the camera frame, so t_hit is depth
    miss = ~np.isfinite(z)  # none in a closed room, but be safe
    z[miss] = 0.0
    gid = np.where(miss, 0, hit["geometry_ids"].numpy())
    n = hit["primitive_normals"].numpy()
    cos = np.einsum("ij,ij->i", n, dirs) * inv_length  # cosine between normal and ray
    n[cos > 0] *= -1  # make normals face the camera
    rgb = surface_colour(origin + z[:, None] * dirs, n, gid, materials, spec.seed)
    rgb *= np.float32(255.0)
    if spec.noise:  # Kinect-like: axial noise growing with z^2, holes at grazing angles
        rng = np.random.default_rng([spec.seed, 3, index])
        z += (0.0012 + 0.0019 * (z - 0.4) ** 2) * rng.standard_normal(z.size, np.float32)
        grazing = (np.float32(0.31) - np.abs(cos)) / np.float32(0.1)  # 0 below 72, 1 above 78 deg
        z[rng.random(z.size, np.float32) < grazing] = 0.0
        rgb += np.float32(2.0) * rng.standard_normal(rgb.shape, np.float32)
    z[miss] = 0.0
    rgb[miss] = 0.0
    colour = np.clip(rgb + 0.5, 0, 255).astype(np.uint8).reshape(spec.height, spec.width, 3)
    return colour, z.reshape(spec.height, spec.width)


HEADERS = {  # the comment lines that start the TUM text files
    "rgb.txt": "# color images\n# timestamp filename\n",
    "depth.txt": "# depth maps (uint16 PNG, depth_scale 5000 as in TUM)\n# timestamp filename\n",
    "associations.txt": "",
    "groundtruth.txt": "# exact ground truth trajectory, T_world_camera (camera: x right, y down, "
    "z forward)\n# timestamp tx ty tz qx qy qz qw\n",
}
README = """Synthetic demo RGB-D sequence made by server.datasets.demo, generator version {version}:
a procedurally textured room ray cast with Open3D along a hand-held-like 6-DoF path, with exact
ground truth. Spec: {spec}

Layout (TUM RGB-D): rgb/*.jpg (JPEG quality 95), depth/*.png (uint16, depth_scale 5000,
0 = no measurement), rgb.txt depth.txt associations.txt groundtruth.txt ('timestamp tx ty tz
qx qy qz qw', T_world_camera), intrinsics.json (fx fy cx cy width height depth_scale).
"""


def _write_index(folder: Path, spec: DemoSpec, stamps: list[str], poses: np.ndarray) -> None:
    """The text files of the TUM layout, intrinsics.json and README.txt."""
    rgb = [f"{s} rgb/{s}.jpg" for s in stamps]
    depth = [f"{s} depth/{s}.png" for s in stamps]
    gt = [
        f"{s} {' '.join(f'{x:.6f}' for x in T[:3, 3])} "
        + " ".join(f"{x:.9f}" for x in quaternion_from_pose(T))
        for s, T in zip(stamps, poses, strict=True)
    ]
    lines = {"rgb.txt": rgb, "depth.txt": depth, "groundtruth.txt": gt}
    lines["associations.txt"] = [f"{a} {b}" for a, b in zip(rgb, depth, strict=True)]
    for name, header in HEADERS.items():
        (folder / name).write_text(header + "".join(f"{line}\n" for line in lines[name]))
    intrinsics = {k: getattr(spec, k) for k in ("fx", "fy", "cx", "cy", "width", "height")}
    intrinsics["depth_scale"] = DEPTH_SCALE
    (folder / "intrinsics.json").write_text(json.dumps(intrinsics, indent=1))
    readme = README.format(version=GENERATOR_VERSION, spec=json.dumps(asdict(spec)))
    (folder / "README.txt").write_text(readme)


def generate_demo_sequence(
    out_dir: Path, spec: DemoSpec = DemoSpec(), progress: bool = True
) -> Path:
    """Render ``spec`` into ``out_dir`` (replaced if present) in the TUM RGB-D layout, with a
    ``.complete`` marker. Writes into a temporary sibling folder first and renames it at the end,
    so a half-written folder is never taken for a finished one. Returns ``out_dir``."""
    out_dir = Path(out_dir)
    tmp = out_dir.with_name(f".{out_dir.name}.tmp-{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    (tmp / "rgb").mkdir(parents=True)
    (tmp / "depth").mkdir()
    start = time.perf_counter()
    scene, materials = build_scene(spec)
    poses = camera_poses(spec)
    stamps = [f"{START_TIME + i / spec.fps:.6f}" for i in range(spec.frames)]
    for i in tqdm(range(spec.frames), desc="demo sequence", unit="frame", disable=not progress):
        colour, depth = render_frame(scene, materials, poses[i], spec, i)
        bgr = cv2.cvtColor(colour, cv2.COLOR_RGB2BGR)
        cv2.imwrite(str(tmp / f"rgb/{stamps[i]}.jpg"), bgr, [cv2.IMWRITE_JPEG_QUALITY, 95])
        depth_units = np.clip(np.rint(depth * DEPTH_SCALE), 0, 65535).astype(np.uint16)
        cv2.imwrite(str(tmp / f"depth/{stamps[i]}.png"), depth_units)
    _write_index(tmp, spec, stamps, poses)
    (tmp / ".complete").write_text(f"{spec.key()}\n")
    shutil.rmtree(out_dir, ignore_errors=True)
    os.replace(tmp, out_dir)
    elapsed = time.perf_counter() - start
    logger.info("demo sequence: %d frames in %.1f s -> %s", spec.frames, elapsed, out_dir)
    return out_dir


def demo_sequence_path(
    spec: DemoSpec = DemoSpec(), cache_dir: Path | None = None, progress: bool = True
) -> Path:
    """The cached demo sequence for ``spec``, generated first if absent.

    Cache root: ``cache_dir``, else the environment variable ``DRONESIM_CACHE``, else
    ``~/.cache/dronesim``; the folder is ``demo-<spec.key()>``.
    """
    root = Path(cache_dir or os.environ.get("DRONESIM_CACHE") or Path.home() / ".cache/dronesim")
    folder = root / f"demo-{spec.key()}"
    if (folder / ".complete").is_file():
        logger.debug("using cached demo sequence %s", folder)
        return folder
    root.mkdir(parents=True, exist_ok=True)
    logger.info("generating demo sequence %s", folder)
    return generate_demo_sequence(folder, spec, progress)
