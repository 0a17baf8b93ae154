"""A room: the keyframes and map a session leaves behind, so that a later session can continue in
the same world frame.

On disk a room is a folder (written by :func:`save_room`, read by :func:`load_room`)::

    room.json            format, version, intrinsics, and per keyframe its id, frame index,
                         T_world_keyframe (4x4, metres, row-major); the sessions that made it
    keyframes/kf_NNNNNN.npz
                         colour (JPEG bytes), depth (16-bit PNG bytes, millimetres), and the
                         place features: uv (N, 2) px, descriptors (N, 32) ORB, points (N, 3)
                         metres in the keyframe's camera frame
    map.npz              the TSDF fused from the keyframes (server/mapping/tsdf_files.py's format)

Keyframe images are kept (rather than only their features) so that the map can be re-fused
from them, e.g. after their poses are corrected, and so that tracking can follow corners from
them; the depth thumbnail verification uses is recomputed from the stored depth.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from server.atomic import atomic_write
from server.errors import DroneSimError
from server.geometry import Intrinsics
from server.geometry.arrays import Float32Array, FloatArray, GreyImage
from server.mapping.config import TSDFConfig
from server.mapping.tsdf import TSDFMap
from server.registration import TrackResult
from server.registration.config import RegistrationConfig
from server.registration.keyframe import Keyframe, make_keyframe
from server.registration.place import (
    KeyframeDatabase,
    PlaceFeatures,
    depth_thumbnail,
    describe_place,
)
from server.registration.preprocess import clean_depth, to_grey

log = logging.getLogger(__name__)

FORMAT = "dronesim-room"
VERSION = 1
MAP_FILE = "map.npz"
META_FILE = "room.json"


class RoomError(DroneSimError):
    """A room folder that cannot be read, or does not fit the camera."""


@dataclass
class RoomKeyframe:
    """One keyframe of a room: its pose in the room's world frame, its images, its features.

    colour: (H, W, 3) RGB uint8; depth: (H, W) float32 metres (0 = none), as the sensor gave it.
    """

    id: int
    frame_index: int  # in the session that made it
    T_world_keyframe: FloatArray  # 4x4, metres
    colour: GreyImage
    depth: Float32Array
    place: PlaceFeatures
    # The images as the keyframe's file holds them (JPEG, 16-bit PNG): encoded once, by
    # ``encoded`` (offline ``track`` does it behind tracking, before the room is saved).
    _encoded: tuple[np.ndarray, np.ndarray] | None = field(default=None, repr=False)

    def encoded(self) -> tuple[np.ndarray, np.ndarray]:
        """(colour JPEG bytes, depth 16-bit PNG bytes in millimetres), as uint8 arrays."""
        if self._encoded is None:
            ok_c, colour = cv2.imencode(".jpg", cv2.cvtColor(self.colour, cv2.COLOR_RGB2BGR))
            mm = np.clip(np.nan_to_num(self.depth) * 1000.0 + 0.5, 0, 65535).astype(np.uint16)
            ok_d, depth = cv2.imencode(".png", mm)
            if not (ok_c and ok_d):
                raise RoomError(f"cannot encode the images of keyframe {self.id}")
            self._encoded = (
                np.asarray(colour, np.uint8).ravel(),
                np.asarray(depth, np.uint8).ravel(),
            )
        return self._encoded


@dataclass
class Room:
    """Keyframes and map in one world frame, seen with one camera."""

    intrinsics: Intrinsics
    keyframes: list[RoomKeyframe] = field(default_factory=list)
    map: TSDFMap | None = None
    sessions: list[dict[str, Any]] = field(default_factory=list)  # what made the room

    def database(self) -> KeyframeDatabase:
        """The keyframes' place features, for relocalisation."""
        db = KeyframeDatabase()
        for kf in self.keyframes:
            db.add(kf.id, kf.T_world_keyframe, kf.place)
        return db

    def keyframe(self, keyframe_id: int) -> RoomKeyframe:
        for kf in self.keyframes:
            if kf.id == keyframe_id:
                return kf
        raise KeyError(keyframe_id)

    def tracking_keyframes(self, cfg: RegistrationConfig) -> list[Keyframe]:
        """The tracker's keyframes (corners, dense model) rebuilt from the stored images."""
        return [
            make_keyframe(
                kf.id,
                kf.frame_index,
                kf.T_world_keyframe,
                to_grey(kf.colour),
                clean_depth(kf.depth, cfg.depth),
                self.intrinsics,
                cfg,
            )
            for kf in self.keyframes
        ]

    def add_tracked(
        self,
        result: TrackResult,
        colour: GreyImage,
        depth: Float32Array,
        frame_index: int,
        cfg: RegistrationConfig,
    ) -> bool:
        """Add the frame of a tracker's ``result`` (after ``update_keyframe``) when it became a
        keyframe; True if it did. colour RGB uint8, depth metres, as given to the tracker."""
        if not result.new_keyframe:
            return False
        self.keyframes.append(
            room_keyframe(
                result.keyframe_id,
                frame_index,
                result.T_world_camera,
                colour,
                depth,
                self.intrinsics,
                cfg,
            )
        )
        return True

    def fuse_map(self, config: TSDFConfig | None = None) -> TSDFMap:
        """A TSDF fused from every keyframe at its pose (replaces ``map``)."""
        tsdf = TSDFMap(config)
        self.fuse_into(tsdf, self.keyframes)
        self.map = tsdf
        return tsdf

    def fuse_into(self, tsdf: TSDFMap, keyframes: list[RoomKeyframe]) -> None:
        """Integrate ``keyframes`` (this room's) into ``tsdf`` at their poses, in order."""
        for kf in keyframes:
            tsdf.integrate(kf.colour, kf.depth, self.intrinsics, kf.T_world_keyframe)


def room_keyframe(
    kf_id: int,
    frame_index: int,
    T_world_keyframe: FloatArray,
    colour: GreyImage,
    depth: Float32Array,
    K: Intrinsics,
    cfg: RegistrationConfig,
) -> RoomKeyframe:
    """A room keyframe from a tracked frame: its place features are computed here."""
    grey, clean = to_grey(colour), clean_depth(depth, cfg.depth)
    place = describe_place(grey, clean, K, cfg.place, cfg.depth)
    return RoomKeyframe(kf_id, frame_index, T_world_keyframe.copy(), colour, depth, place)


def same_camera(room: Room, K: Intrinsics, tolerance: float = 0.02) -> bool:
    """Whether ``K`` is the room's camera: size equal, focal lengths and centre within
    ``tolerance`` relative."""
    R = room.intrinsics
    return (R.width, R.height) == (K.width, K.height) and bool(
        np.allclose([K.fx, K.fy, K.cx, K.cy], [R.fx, R.fy, R.cx, R.cy], rtol=tolerance)
    )


def check_camera(room: Room, K: Intrinsics) -> None:
    """Raise RoomError unless ``K`` is the room's camera (``same_camera``): a run that adds its
    keyframes to the room (one camera per room file) needs it."""
    if not same_camera(room, K):
        R = room.intrinsics
        raise RoomError(f"the room was mapped with another camera ({R}), this one is {K}")


# ---- files ------------------------------------------------------------------------------------
def save_room(room: Room, folder: str | Path) -> dict[str, int]:
    """Write ``room`` into ``folder`` (created; files there are replaced). The map is re-fused
    from the keyframes when ``room.map`` is None. Returns the bytes written per part."""
    folder = Path(folder)
    sizes = {"keyframes": 0, "map": 0, "meta": 0}
    for kf in room.keyframes:
        sizes["keyframes"] += write_keyframe(folder, kf)
    (room.map or room.fuse_map()).save(folder / MAP_FILE)
    sizes["map"] = (folder / MAP_FILE).stat().st_size
    entries = [(kf.id, kf.frame_index, kf.T_world_keyframe) for kf in room.keyframes]
    sizes["meta"] = write_room_meta(folder, room.intrinsics, entries, room.sessions)
    return sizes


def write_room_meta(
    folder: Path,
    K: Intrinsics,
    keyframes: list[tuple[int, int, FloatArray]],
    sessions: list[dict[str, Any]],
) -> int:
    """Write ``room.json`` (last: a folder with it is a whole room) for keyframes given as
    (id, frame index, T_world_keyframe) whose files are in ``folder``; returns its size."""
    meta = {
        "format": FORMAT,
        "version": VERSION,
        "saved": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "intrinsics": {
            "fx": K.fx, "fy": K.fy, "cx": K.cx, "cy": K.cy, "width": K.width, "height": K.height
        },
        "keyframes": [
            {"id": i, "frame_index": f, "T_world_keyframe": np.round(T, 9).ravel().tolist()}
            for i, f, T in keyframes
        ],
        "sessions": sessions,
    }  # fmt: skip
    text = json.dumps(meta, indent=1)
    atomic_write(
        folder / META_FILE, lambda tmp: Path(tmp).write_text(text), suffix=".json", mode=0o644
    )
    return len(text)


def keyframe_path(folder: Path, kf_id: int) -> Path:
    return folder / "keyframes" / f"kf_{kf_id:06d}.npz"


def write_keyframe(folder: Path, kf: RoomKeyframe) -> int:
    """Write one keyframe's file into the room ``folder`` unless it is there (a keyframe never
    changes once written; its pose lives in room.json); returns the file's size."""
    path = keyframe_path(folder, kf.id)
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        _write_keyframe(path, kf)
    return path.stat().st_size


def link_keyframes(source: Path, folder: Path, ids: list[int]) -> None:
    """Give the room ``folder`` the keyframe files ``ids`` of the room ``source`` (hard links,
    copies where the file system has none)."""
    for kf_id in ids:
        src, dst = keyframe_path(source, kf_id), keyframe_path(folder, kf_id)
        if dst.exists():
            continue
        dst.parent.mkdir(parents=True, exist_ok=True)
        try:
            os.link(src, dst)
        except OSError:
            shutil.copyfile(src, dst)


def _write_keyframe(path: Path, kf: RoomKeyframe) -> None:
    colour, depth = kf.encoded()
    arrays: dict[str, Any] = {
        "colour_jpg": colour,
        "depth_png": depth,
        "uv": kf.place.uv,
        "descriptors": kf.place.descriptors,
        "points": kf.place.points,
    }

    def write(tmp: str) -> None:
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)

    atomic_write(path, write, suffix=".npz", mode=0o644)


def load_room(folder: str | Path, cfg: RegistrationConfig | None = None) -> Room:
    """Read a room written by :func:`save_room`; RoomError names what is wrong."""
    folder = Path(folder)
    cfg = cfg or RegistrationConfig()
    meta_path = folder / META_FILE
    if not meta_path.is_file():
        raise RoomError(f"{folder} is not a room: no {META_FILE}")
    try:
        meta = json.loads(meta_path.read_text())
        if meta.get("format") != FORMAT or meta.get("version") != VERSION:
            raise RoomError(
                f"{meta_path}: format {meta.get('format')!r} version {meta.get('version')!r}, "
                f"expected {FORMAT!r} version {VERSION}"
            )
        K = Intrinsics(**meta["intrinsics"])
        room = Room(K, sessions=list(meta.get("sessions", [])))
        for entry in meta["keyframes"]:
            T = np.asarray(entry["T_world_keyframe"], dtype=np.float64).reshape(4, 4)
            room.keyframes.append(
                _read_keyframe(folder, int(entry["id"]), int(entry["frame_index"]), T, K, cfg)
            )
    except (KeyError, TypeError, ValueError, OSError) as exc:
        raise RoomError(f"cannot read the room in {folder}: {exc!r}") from exc
    if (folder / MAP_FILE).is_file():
        room.map = TSDFMap.load(folder / MAP_FILE)
    return room


def read_keyframe_images(folder: Path, kf_id: int) -> tuple[GreyImage, Float32Array]:
    """A keyframe's colour (H, W, 3) RGB uint8 and depth (H, W) float32 metres from its file in
    the room ``folder`` (a map re-fused from the keyframes reads only these)."""
    path = keyframe_path(folder, kf_id)
    with np.load(path) as z:
        colour_bgr = cv2.imdecode(z["colour_jpg"], cv2.IMREAD_COLOR)
        mm = cv2.imdecode(z["depth_png"], cv2.IMREAD_UNCHANGED)
    if colour_bgr is None or mm is None or mm.dtype != np.uint16:
        raise RoomError(f"{path}: the keyframe's images do not decode")
    colour = np.asarray(cv2.cvtColor(colour_bgr, cv2.COLOR_BGR2RGB), dtype=np.uint8)
    return colour, mm.astype(np.float32) / 1000.0


def _read_keyframe(
    folder: Path,
    kf_id: int,
    frame_index: int,
    T: FloatArray,
    K: Intrinsics,
    cfg: RegistrationConfig,
) -> RoomKeyframe:
    colour, depth = read_keyframe_images(folder, kf_id)
    with np.load(keyframe_path(folder, kf_id)) as z:
        uv, descriptors, points = z["uv"], z["descriptors"], z["points"]
    # The depth thumbnail is derived data: recomputed, as describe_place makes it.
    small, K_small = depth_thumbnail(clean_depth(depth, cfg.depth), K, cfg.place.depth_shrink)
    place = PlaceFeatures(
        uv.astype(np.float32),
        descriptors.astype(np.uint8),
        points.astype(np.float64),
        small,
        K_small,
    )
    return RoomKeyframe(kf_id, frame_index, T, colour, depth, place)
