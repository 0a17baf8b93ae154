"""The phone page: ``client_web/`` at ``/``, its vendored npm modules, the protocol definition
and the bundled demo sequence that the page's replay mode streams.

| path | what |
|---|---|
| ``/`` | the page (``client_web/index.html``) |
| ``/check`` | the device check: what a phone's browser offers live AR (``check.html``) |
| ``/app/{path}`` | the page's own files (``client_web/``: js, css, icons) |
| ``/vendor/{package}/{path}`` | the npm packages the page imports (three, @msgpack/msgpack, uqr) |
| ``/protocol.json`` | ``shared/protocol.json``, unchanged: the page validates against it |
| ``/api/demo?preset=`` | a demo sequence's index: camera, sizes, depth scale and frame file URLs |
| ``/api/demo/files/{path}?preset=`` | one colour JPEG or depth PNG of that sequence |

The page needs no internet: everything it loads comes from here. Files are looked up under a
fixed root and a path that leaves it (``..``, absolute, links) is a 404. Both roots are package
data (``importlib.resources``): the ``client_web`` and ``shared`` packages of a checkout, or of an
installed wheel, which carries only the module files the page imports (pyproject.toml).
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import threading
from importlib.resources import files
from pathlib import Path

import numpy as np
from fastapi import APIRouter, HTTPException
from fastapi.responses import FileResponse

from server.datasets.demo import DemoSpec, demo_sequence_path
from server.datasets.replay_export import replay_index
from server.datasets.tum import read_file_list, read_ground_truth, tum_intrinsics
from server.evaluation.trajectory import associate

log = logging.getLogger(__name__)
router = APIRouter(tags=["client"])


def package_folder(package: str) -> Path:
    """The folder of a package's data on disk. FileResponse serves files of the file system; a
    checkout, an editable install and an installed wheel all have them there (a wheel is never
    imported from inside its zip)."""
    folder = files(package)
    if not isinstance(folder, Path):
        raise RuntimeError(f"package {package!r} is not a folder on disk: {folder}")
    return folder


CLIENT_DIR = package_folder("client_web")
VENDOR_DIR = CLIENT_DIR / "node_modules"
# The very file the server's protocol validator reads (files("shared") / "protocol.json").
PROTOCOL_FILE = package_folder("shared") / "protocol.json"
VENDOR_PACKAGES = ("three", "@msgpack/msgpack", "uqr")  # the only npm packages served
APP_FOLDERS = ("js", "css", "assets")  # the page's own files; never package.json or node_modules
DEMO_FOLDERS = ("rgb", "depth")
MEDIA_TYPES = {
    ".js": "text/javascript",
    ".mjs": "text/javascript",
    ".css": "text/css",
    ".json": "application/json",
    ".html": "text/html",
    ".svg": "image/svg+xml",
    ".png": "image/png",
    ".jpg": "image/jpeg",
    ".map": "application/json",
}
# The page is small and changes with the server: revalidate every time (ETag / Last-Modified).
NO_CACHE = {"Cache-Control": "no-cache"}

# The demo sequences the page can replay: the bundled default (640x480, 150 frames), a small
# one (320x240, 90 frames: a quarter of the bytes, for slow links and quick tests), and the
# whole walk at the small size played forward then back ("loop", 299 frames: it returns to
# where it started, so loop closure has a loop to find and the page shows the map corrected;
# the small one's 90 frames are too short: the tracker's recent keyframes still reach back).
_SMALL = DemoSpec(frames=90, width=320, height=240, fx=262.5, fy=262.5, cx=159.5, cy=119.5)
DEMO_PRESETS = {
    "default": DemoSpec(),
    "small": _SMALL,
    "loop": dataclasses.replace(_SMALL, frames=150),
}
THERE_AND_BACK = {"loop"}  # presets whose frames play forward, then backward to the first

_demo_lock = threading.Lock()
_demo_indexes: dict[str, tuple[Path, dict]] = {}


def _file(root: Path, relative: str, headers: dict | None = None) -> FileResponse:
    """The file ``relative`` below ``root``; 404 for anything outside it or not a plain file."""
    base = root.resolve()
    try:
        path = (base / relative).resolve()
    except (OSError, RuntimeError) as exc:
        raise HTTPException(404, "no such file") from exc
    if not path.is_relative_to(base) or not path.is_file():
        raise HTTPException(404, "no such file")
    return FileResponse(path, media_type=MEDIA_TYPES.get(path.suffix.lower()), headers=headers)


@router.get("/", include_in_schema=False)
def page() -> FileResponse:
    """The phone page."""
    return _file(CLIENT_DIR, "index.html", NO_CACHE)


@router.get("/check", include_in_schema=False)
def check_page() -> FileResponse:
    """The device check: what this phone's browser offers live AR, as a JSON report."""
    return _file(CLIENT_DIR, "check.html", NO_CACHE)


@router.get("/app/{path:path}", include_in_schema=False)
def app_file(path: str) -> FileResponse:
    """The page's scripts, styles and images."""
    if path.split("/", 1)[0] not in APP_FOLDERS:
        raise HTTPException(404, "no such file")
    return _file(CLIENT_DIR, path, NO_CACHE)


@router.get("/vendor/{path:path}", include_in_schema=False)
def vendor_file(path: str) -> FileResponse:
    """A file of one of the npm packages the page imports (installed by ``npm ci``)."""
    if not any(path.startswith(f"{package}/") for package in VENDOR_PACKAGES):
        raise HTTPException(404, "no such package")
    if not VENDOR_DIR.is_dir():
        raise HTTPException(
            503,
            f"{VENDOR_DIR} is missing: run scripts/setup.sh (npm ci in client_web) in a checkout;"
            " a wheel must be built after it",
        )
    return _file(VENDOR_DIR, path, {"Cache-Control": "public, max-age=3600"})


@router.get("/protocol.json", tags=["client"])
def protocol_definition() -> FileResponse:
    """The wire protocol (``shared/protocol.json``): the definition the server itself uses."""
    return _file(PROTOCOL_FILE.parent, PROTOCOL_FILE.name, NO_CACHE)


def _gravity(folder: Path) -> list[float] | None:
    """Gravity in the first camera's frame (OpenCV axes), from the ground truth of a sequence
    whose world frame is z-up (the demo's): R_world_camera^T @ (0, 0, -1)."""
    truth = read_ground_truth(folder / "groundtruth.txt")
    if truth is None or len(truth.poses) == 0:
        return None
    down = truth.poses[0][:3, :3].T @ np.array([0.0, 0.0, -1.0])
    return [float(v) for v in down]


def build_demo_index(folder: Path, files_url: str = "/api/demo/files", query: str = "") -> dict:
    """The page's view of a TUM-layout sequence: camera, sizes, depth scale, gravity and one
    ``{timestamp, colour, depth}`` entry (file URLs) per associated colour/depth pair."""
    K, depth_scale = tum_intrinsics(folder, None, None)
    rgb_stamps, rgb_names = read_file_list(folder / "rgb.txt")
    depth_stamps, depth_names = read_file_list(folder / "depth.txt")
    idx_rgb, idx_depth = associate(rgb_stamps, depth_stamps, 0.02)
    times = [float(rgb_stamps[i]) for i in idx_rgb]
    frames = [
        {
            "timestamp": t,
            "colour": f"{files_url}/{rgb_names[i]}{query}",
            "depth": f"{files_url}/{depth_names[j]}{query}",
        }
        for t, i, j in zip(times, idx_rgb, idx_depth, strict=True)
    ]
    return replay_index(folder.name, K, depth_scale, _gravity(folder), frames)


def there_and_back(index: dict) -> dict:
    """A replay index whose frames play forward, then backward to the first (the last is not
    repeated), stamped on at the sequence's own rate: a camera that walks a path and comes back
    along it, as a user who returns to where they started."""
    frames = index["frames"]
    if len(frames) < 2:
        return index
    step = 1.0 / index["fps"]
    start = frames[0]["timestamp"]
    order = [*frames, *frames[-2::-1]]
    played = [{**f, "timestamp": round(start + i * step, 6)} for i, f in enumerate(order)]
    return {**index, "name": f"{index['name']} there and back", "frames": played}


def _demo(preset: str) -> tuple[Path, dict]:
    """A demo preset's folder and index; the first call generates the sequence (cached on
    disk, ~/.cache/dronesim)."""
    spec = DEMO_PRESETS.get(preset)
    if spec is None:
        raise HTTPException(404, f"no demo preset {preset!r}; presets: {', '.join(DEMO_PRESETS)}")
    with _demo_lock:
        if preset not in _demo_indexes:
            folder = demo_sequence_path(spec, progress=False)
            query = "" if preset == "default" else f"?preset={preset}"
            index = build_demo_index(folder, query=query)
            if preset in THERE_AND_BACK:
                index = there_and_back(index)
            _demo_indexes[preset] = (folder, index)
            log.info("demo preset %s for the page's replay: %s", preset, folder)
        return _demo_indexes[preset]


@router.get("/api/demo", tags=["client"])
async def demo_index(preset: str = "default") -> dict:
    """A bundled demo sequence (generated on first use, then cached): intrinsics, image sizes,
    depth scale, gravity in the first camera frame, and per frame the URLs of its colour JPEG
    and 16-bit depth PNG, for the page's replay mode. ``preset``: default (640x480, 150
    frames), small (320x240, 90 frames) or loop (150 frames at 320x240 forward then back, 299
    frames)."""
    _, index = await asyncio.to_thread(_demo, preset)
    return index


@router.get("/api/demo/files/{path:path}", tags=["client"])
async def demo_file(path: str, preset: str = "default") -> FileResponse:
    """One file of a demo sequence: ``rgb/<t>.jpg`` or ``depth/<t>.png``."""
    if path.split("/", 1)[0] not in DEMO_FOLDERS:
        raise HTTPException(404, "no such file")
    folder, _ = await asyncio.to_thread(_demo, preset)
    return _file(folder, path, {"Cache-Control": "public, max-age=86400"})
