"""A session's map: TSDF fusion, the map preview and the drone's occupancy grid, in a process of
its own beside the session's tracking: a process worker's sibling, or a Ray actor's child
(server/sessions/processes/actor_host.py); or, in a Session made in-process (tests), in the
calling thread.

Why a process: Open3D's ``VoxelBlockGrid.integrate`` holds the GIL for the whole call (30-50 ms
for a 640x480 frame), so in a thread beside tracking every fusion stalls the tracker. Measured
on 7scenes_a at 15 fps with a fusion every 200 ms (benchmarks/beside_tracking.py):
tracking p95 26.5 ms alone, 65.7 ms beside fusion in a thread, 24.8 ms beside fusion in
another process.
"""

from __future__ import annotations

import logging
import math
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from server.geometry import Intrinsics
from server.mapping.config import MappingConfig
from server.mapping.preview import MapPreview
from server.mapping.tsdf import MapError, TSDFMap
from server.rooms.room import read_keyframe_images
from server.sessions.errors import SessionError
from server.sessions.failures import SessionLog
from server.sessions.processes.ipc import Proxy, TurnLock, prepare_child, serve
from server.sessions.processes.priority import MAPPING_NICE
from server.sessions.processes.room_map import RoomAddress, serve_room
from server.sessions.store import hold_writers_lock

log = logging.getLogger(__name__)

MAP_FILES = ("map.npz", "map.ply")  # what a snapshot of the map writes
# A periodic snapshot (crash insurance) writes map.npz uncompressed (~100 ms less CPU, ~3x the
# size until the session's last snapshot compresses it) and map.ply, the surface points
# extracted from the whole map (~90 ms), at most this often: the npz holds every observation.
PERIODIC_PLY_EVERY_S = 30.0


@dataclass
class Fused:
    """What one fused frame gave: new preview points (world metres, RGB) and, when asked for,
    the drone's occupancy for the region changed since the last time (``TSDFMap.
    occupancy_update``: origin, occupied, observed in the flight frame), or None;
    ``occupancy_error`` says why the occupancy asked for could not be had (the frame is fused
    all the same). ``surface``: the map has a surface (``TSDFMap.has_surface``: its mesh and
    surface points can be downloaded)."""

    points: np.ndarray
    colours: np.ndarray
    total_points: int
    occupancy: tuple[np.ndarray, np.ndarray, np.ndarray] | None
    occupancy_error: str | None = None
    stats: dict = field(default_factory=dict)  # the map's ``stats()`` after this frame
    surface: bool = False


@dataclass
class Rebuilt:
    """A map re-fused from keyframes at corrected poses, now the session's map: its whole
    preview (world metres, RGB: the client's preview restarts from it), the drone's whole
    occupancy grid when asked for (as ``Fused.occupancy``, flight frame) or None, and what the
    rebuild cost (``keyframes`` re-read and fused, ``cpu_ms`` of the mapping process)."""

    points: np.ndarray
    colours: np.ndarray
    total_points: int
    occupancy: tuple[np.ndarray, np.ndarray, np.ndarray] | None
    occupancy_error: str | None
    stats: dict
    keyframes: int
    cpu_ms: float
    surface: bool = False  # as Fused's, of the new map


@dataclass
class _Rebuild:
    """A rebuild in progress: the new map, its preview, and the keyframes still to fuse as
    (id, T_world_keyframe at its corrected pose), read from ``folder``'s keyframe files."""

    map: TSDFMap
    preview: MapPreview
    folder: Path
    K: Intrinsics
    todo: list[tuple[int, np.ndarray]]
    points: list[np.ndarray] = field(default_factory=list)
    colours: list[np.ndarray] = field(default_factory=list)
    keyframes: int = 0
    cpu_s: float = 0.0


class Mapper:
    """The map of one session, used by one caller at a time (the session's mapping thread; the
    status and downloads come from other threads, hence the lock).

    After a loop closure the map is rebuilt from the keyframes at their corrected poses, in
    steps the caller interleaves with fusion (``rebuild_start``, ``rebuild_step``,
    ``rebuild_finish``): the old map serves until the new one replaces it at once."""

    def __init__(self, config: MappingConfig) -> None:
        self.map = TSDFMap(config.tsdf)
        self.preview = MapPreview()
        self._ply_at = -math.inf  # time.monotonic() of the last map.ply written
        self.preview_points = config.preview_points
        # The previews of the phones that joined this map's room (server/sessions/processes/
        # room_map.py), by reader name: each phone is sent what its own frames show first.
        self.joined_previews: dict[str, MapPreview] = {}
        self._rebuild: _Rebuild | None = None
        # Whether the map has a surface yet: checked after each fusion until it has (a map's
        # voxels only gain observations), then known for good.
        self._surface = False
        # In turns: the room's phones fuse into this map from threads of their own, each frame
        # after frame (ipc.TurnLock).
        self._lock = TurnLock()

    def fuse(
        self,
        colour: np.ndarray,
        depth: np.ndarray,
        K: Intrinsics,
        T_world_camera: np.ndarray,
        occupancy: tuple[float, np.ndarray] | None = None,
        rebuild_pose: np.ndarray | None = None,
        reader: str = "",
    ) -> Fused:
        """Integrate a frame (colour RGB uint8, depth metres at K's size, T_world_camera 4x4);
        ``occupancy``: (cell edge in metres, R_flight_world) to also return the drone's grid
        for what changed, or None. ``rebuild_pose``: while a rebuild is in progress, also fuse
        the frame into the new map at this pose (its T_world_camera in the corrected world).
        ``reader``: the phone whose frame it is, "" for the session's own (a phone that joined
        the room has its own preview and drone: ``TSDFMap.occupancy_update``)."""
        with self._lock:
            rebuild = self._rebuild
            if rebuild is not None and rebuild_pose is not None:
                self._rebuild_fuse(rebuild, colour, depth, K, rebuild_pose)
            self.map.integrate(colour, depth, K, T_world_camera)
            self._surface = self._surface or self.map.has_surface()
            preview = self.preview if not reader else self.joined_previews[reader]
            points, colours = preview.new_points(
                colour, depth, K, T_world_camera, self.preview_points
            )
            grid, error = None, None
            if occupancy is not None:
                try:
                    grid = self.map.occupancy_update(*occupancy, reader=reader)
                except Exception as exc:  # the drone's map misses this one; the TSDF has it
                    error = f"{type(exc).__name__}: {exc}"
            stats = self.map.stats()
            return Fused(points, colours, preview.total, grid, error, stats, self._surface)

    def add_reader(self, name: str) -> None:
        """A phone that joined the room fuses into this map as reader ``name`` (``fuse``)."""
        with self._lock:
            self.joined_previews.setdefault(name, MapPreview())

    # ---- a rebuild after a loop closure -------------------------------------------------------
    def rebuild_start(
        self, folder: str | Path, keyframes: list[tuple[int, np.ndarray]], K: Intrinsics
    ) -> None:
        """Start a new map from the keyframes (id, T_world_keyframe 4x4 metres, corrected) whose
        files are in the room ``folder`` (read here, by path: the images never cross the pipe).
        A rebuild still in progress is dropped for this one."""
        with self._lock:
            self._rebuild = _Rebuild(
                TSDFMap(self.map.config),
                MapPreview(),
                Path(folder),
                K,
                [(int(i), np.asarray(T, np.float64)) for i, T in keyframes],
            )

    def rebuild_step(self, count: int = 1) -> int:
        """Fuse up to ``count`` more keyframes into the new map (each read, then fused); returns
        how many are left (0: ready for ``rebuild_finish``). Raises MapError with no rebuild
        started."""
        with self._lock:
            rebuild = self._require_rebuild()
            for _ in range(min(count, len(rebuild.todo))):
                kf_id, T = rebuild.todo.pop(0)
                colour, depth = read_keyframe_images(rebuild.folder, kf_id)
                self._rebuild_fuse(rebuild, colour, depth, rebuild.K, T)
                rebuild.keyframes += 1
            return len(rebuild.todo)

    def rebuild_finish(self, occupancy: tuple[float, np.ndarray] | None = None) -> Rebuilt:
        """The new map replaces the old one (whatever keyframes are left are fused first); the
        preview restarts from it. ``occupancy``: (cell edge, R_flight_world) for the drone's
        whole grid of the new map."""
        self.rebuild_step(1 << 30)
        with self._lock:
            rebuild = self._require_rebuild()
            self._rebuild = None
            self.map, self.preview = rebuild.map, rebuild.preview
            self._surface = self.map.has_surface()
            grid, error = None, None
            if occupancy is not None:
                try:  # the new map's first update is its whole grid
                    grid = self.map.occupancy_update(*occupancy)
                except Exception as exc:  # the drone keeps its old map; the TSDF is replaced
                    error = f"{type(exc).__name__}: {exc}"
            points = np.concatenate([np.empty((0, 3), np.float32), *rebuild.points])
            colours = np.concatenate([np.empty((0, 3), np.uint8), *rebuild.colours])
            return Rebuilt(
                points,
                colours,
                self.preview.total,
                grid,
                error,
                self.map.stats(),
                rebuild.keyframes,
                rebuild.cpu_s * 1e3,
                self._surface,
            )

    def rebuild_cancel(self) -> None:
        """Drop a rebuild in progress (it failed); the map stays as it is."""
        with self._lock:
            self._rebuild = None

    def _require_rebuild(self) -> _Rebuild:
        if self._rebuild is None:
            raise MapError("no map rebuild in progress")
        return self._rebuild

    def _rebuild_fuse(
        self,
        rebuild: _Rebuild,
        colour: np.ndarray,
        depth: np.ndarray,
        K: Intrinsics,
        T_world_camera: np.ndarray,
    ) -> None:
        cpu0 = time.thread_time()
        rebuild.map.integrate(colour, depth, K, T_world_camera)
        points, colours = rebuild.preview.new_points(
            colour, depth, K, T_world_camera, self.preview_points
        )
        rebuild.points.append(points)
        rebuild.colours.append(colours)
        rebuild.cpu_s += time.thread_time() - cpu0

    def occupancy(
        self, voxel_m: float, R_flight_world: np.ndarray, reader: str = ""
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The drone's occupancy for the region the frames fused since the last request changed
        (as ``Fused.occupancy``), or None when nothing changed: the catch-up after the last
        frames, which asked for none (it is asked for at most every flight_map_interval_s).
        ``reader``: as ``fuse``'s."""
        with self._lock:
            return self.map.occupancy_update(voxel_m, R_flight_world, reader=reader)

    def load(self, path: str) -> None:
        """Start from a saved map (a room's ``map.npz``) instead of an empty one; its voxel
        size and block resolution must be this session's."""
        loaded = TSDFMap.load(path, self.map.config)
        surface = loaded.has_surface()
        with self._lock:
            self.map, self._surface = loaded, surface

    def stats(self, wait: bool = True) -> dict | None:
        """The map's figures (``TSDFMap.stats``); None instead of waiting when the map is busy
        (a fusion in progress) and ``wait`` is False."""
        if not self._lock.acquire(blocking=wait):
            return None
        try:
            return self.map.stats()
        finally:
            self._lock.release()

    def save(self, folder: str | Path, periodic: bool = False) -> list[str]:
        """Write the map's snapshot files into ``folder`` (map.npz, and map.ply once there is a
        surface); returns the names written. ``periodic``: a periodic snapshot, for which the
        npz is not compressed and map.ply is written every PERIODIC_PLY_EVERY_S only (the
        previous one stays in the session's folder meanwhile)."""
        if self.map.stats()["frames_integrated"] == 0:
            return []
        folder = Path(folder)
        with self._lock:
            self.map.save(folder / "map.npz", compress=not periodic)
            if periodic and time.monotonic() - self._ply_at < PERIODIC_PLY_EVERY_S:
                return ["map.npz"]
            try:
                self.map.write_point_cloud_ply(folder / "map.ply")
            except MapError:  # too few observations for a surface yet
                return ["map.npz"]
            self._ply_at = time.monotonic()
        return list(MAP_FILES)

    def download(self, name: str) -> bytes:
        """``map.ply`` (surface points) or ``mesh.ply``, as the bytes of the file."""
        write = {"map.ply": self.map.write_point_cloud_ply, "mesh.ply": self.map.write_mesh_ply}[
            name
        ]
        with tempfile.TemporaryDirectory() as tmp, self._lock:
            path = Path(tmp) / name
            try:
                write(path)
            except MapError:  # said without the server's temporary path
                raise MapError("the map has no surface yet") from None
            return path.read_bytes()

    def close(self) -> None:
        pass


# ---- the same, in a process of its own ---------------------------------------------------------


class MapperLost(SessionError):
    """The session's mapping process is gone: the session cannot go on. ``why``: what ended
    it, when known, as a clause to add to that (", ...")."""

    def __init__(self, message: str, why: str = "") -> None:
        super().__init__("session_failed", message)
        self.why = why


def mapper_main(
    conn,
    config: MappingConfig,
    threads: int,
    session_id: str = "",
    data_dir: str | None = None,
    room: RoomAddress | None = None,
) -> None:
    """Entry point of a session's mapping process: serve ``Mapper`` calls until the pipe
    closes (its session stopped, or died). ``data_dir``: where it writes its session's
    snapshots, whose writers lock it holds while it lives (``store.hold_writers_lock``).
    ``room``: where the phones that join the session's room reach this map too."""
    prepare_child(MAPPING_NICE)  # the session's worker decides when it ends
    if data_dir is not None:  # a restarted server cleans only after this process ends
        hold_writers_lock(data_dir)
    import open3d as o3d

    o3d.utility.set_max_threads(threads)
    mapper = Mapper(config)
    session_log = SessionLog(log, session_id)
    phones = None if room is None else serve_room(mapper, room, session_log)
    serve(mapper, conn, session_log)
    if phones is not None:  # the room's map outlives its owner's session while phones map it
        phones.wait()


class MapperClient:
    """A ``Mapper`` in another process, reached over ``conn`` (one call at a time). When that
    process is gone, every call raises MapperLost: a session without its map cannot go on, and
    the session decides how it ends (``Session.fail``)."""

    def __init__(self, conn, why_lost: str = "") -> None:
        """why_lost: what ending the other process would mean (``MapperLost.why``)."""
        self._proxy = Proxy(
            conn, lambda message: MapperLost(message, why_lost), "the session's mapping process"
        )
        self._call = self._proxy.call

    def fuse(self, colour, depth, K, T_world_camera, occupancy=None, rebuild_pose=None) -> Fused:
        return self._call("fuse", colour, depth, K, T_world_camera, occupancy, rebuild_pose)

    def rebuild_start(
        self, folder: str | Path, keyframes: list[tuple[int, np.ndarray]], K: Intrinsics
    ) -> None:
        self._call("rebuild_start", str(folder), keyframes, K)

    def rebuild_step(self, count: int = 1) -> int:
        return self._call("rebuild_step", count)

    def rebuild_finish(self, occupancy: tuple[float, np.ndarray] | None = None) -> Rebuilt:
        return self._call("rebuild_finish", occupancy)

    def rebuild_cancel(self) -> None:
        self._call("rebuild_cancel")

    def occupancy(
        self, voxel_m: float, R_flight_world: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        return self._call("occupancy", voxel_m, R_flight_world)

    def stats(self, wait: bool = True) -> dict | None:
        """As ``Mapper.stats``: None at once when a call (a fusion, a save) is in progress and
        ``wait`` is False, since the mapping process answers one call at a time."""
        if wait:
            return self._call("stats")
        _, stats = self._proxy.call_if_idle("stats")
        return stats  # type: ignore[return-value]

    def save(self, folder: str, periodic: bool = False) -> list[str]:
        return self._call("save", str(folder), periodic)

    def load(self, path: str) -> None:
        self._call("load", str(path))

    def download(self, name: str) -> bytes:
        return self._call("download", name)

    def close(self) -> None:
        """Let the mapping process end (it exits when its pipe closes)."""
        self._proxy.close()
