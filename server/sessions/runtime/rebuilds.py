"""The map's rebuilds after a loop closure (server/sessions/runtime/loop_closing.py), on the mapping
thread: the map re-fused from every keyframe of the session's room at its corrected pose, a few
keyframes at a time between fusions (docs/ARCHITECTURE.md, step 10)."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass

import numpy as np

from server.geometry import Intrinsics
from server.mapping.config import MappingConfig
from server.sessions.processes.mapper import Mapper, MapperClient, MapperLost, Rebuilt
from server.sessions.runtime.counts import SessionCounts
from server.sessions.runtime.loop_closing import Correction, LoopClosing, pose_move_m
from server.sessions.runtime.room_writer import RoomWriter

# (the rebuilt map, T_map: what moves the old map's world into the new one, the last seq)
OnRebuilt = Callable[[Rebuilt, np.ndarray, int], None]


@dataclass
class RebuildFigures:
    """The status's rebuild figures (``loops``)."""

    rebuilds: int = 0
    rebuild_pending: bool = False  # a correction waits for its rebuild, or one is in progress
    rebuilds_skipped: int = 0
    rebuilds_cpu_ms: float = 0.0  # the mapping process's CPU over every rebuild so far
    map_behind_m: float = 0.0  # the most a keyframe moved since the map was fused, m
    last_rebuild_ms: float | None = None
    last_rebuild_cpu_ms: float | None = None
    last_rebuild_keyframes: int | None = None

    def as_dict(self) -> dict:
        figures = asdict(self)
        figures["rebuilds_cpu_ms"] = round(self.rebuilds_cpu_ms, 1)
        figures["map_behind_m"] = round(self.map_behind_m, 4)
        return figures


class MapRebuilds:
    """Rebuilds the map for the newest correction (``want``), from the keyframes ``room``
    wrote, on the mapping thread (``start_if_wanted``, ``step``)."""

    def __init__(
        self,
        mapper: Mapper | MapperClient,
        loops: LoopClosing,
        room: RoomWriter,
        K: Intrinsics,
        cfg: MappingConfig,
        counts: SessionCounts,
        log: logging.LoggerAdapter,
    ) -> None:
        self.mapper = mapper
        self.loops = loops
        self.room = room
        self.K = K
        self.cfg = cfg
        self.counts = counts
        self.log = log
        self._lock = threading.Lock()  # guards _wanted, _figures and _running
        self._wanted: Correction | None = None  # the newest correction not yet rebuilt
        self._figures = RebuildFigures()
        self._running = False  # a correction taken from _wanted is being handled
        # Mapping thread only:
        self.rebuilding: Correction | None = None
        self._t0 = 0.0
        self._map_world = 0  # the world the map and the drone's map are in
        # Each room keyframe's pose in the map (fused there at it), and in the map a rebuild
        # in progress makes: what a correction's move is measured against.
        self._map_poses: dict[int, np.ndarray] = {}
        self._rebuild_poses: dict[int, np.ndarray] = {}

    def want(self, correction: Correction) -> None:
        """A correction came (loop thread): the newest wins."""
        with self._lock:
            self._wanted = correction

    def figures(self) -> dict:
        with self._lock:
            self._figures.rebuild_pending = self._wanted is not None or self._running
            return self._figures.as_dict()

    def _handled(self) -> None:
        """The correction taken is done with: rebuilt (its reset published), skipped or
        failed."""
        with self._lock:
            self._running = False

    def pose_in_rebuild(self, kf_id: int, T_world_camera: np.ndarray, world: int):
        """A keyframe about to be fused during a rebuild: its pose in the new map (it goes into
        both), or None when no rebuild runs."""
        if self.rebuilding is None:
            return None
        T = self.loops.worlds.carry(kf_id, T_world_camera, world, self.rebuilding.world)
        self._rebuild_poses[kf_id] = T
        return T

    def keyframe_fused(self, kf_id: int, T_world_camera: np.ndarray) -> None:
        self._map_poses[kf_id] = T_world_camera

    def start_if_wanted(self) -> None:
        """Start rebuilding the map for the newest correction, from every keyframe written so
        far at its pose in the corrected world; the room's keyframe poses become these. A
        rebuild in progress finishes first (restarting it at every loop would never finish
        while the camera keeps closing loops); corrections that came meanwhile wait, and only
        the newest of them is rebuilt. A correction that moves no keyframe by more than
        ``rebuild_min_move_m`` from its pose in the map leaves the map as it is (counted as
        skipped): the moves add up until one is worth a rebuild."""
        if self.rebuilding is not None:
            return
        with self._lock:
            wanted, self._wanted = self._wanted, None
            self._running = wanted is not None
        if wanted is None:
            return
        entries = self.room.carry_into(self.loops.worlds, wanted.world)
        moves = [pose_move_m(self._map_poses[i], T) for i, T in entries if i in self._map_poses]
        move = max(moves, default=0.0)
        with self._lock:
            self._figures.map_behind_m = move
        if move <= self.cfg.rebuild_min_move_m:
            with self._lock:
                self._figures.rebuilds_skipped += 1
                self._running = False
            self.log.info(
                "world %d moves the map by %.3f m at most: not re-fused", wanted.world, move
            )
            return
        try:
            self.mapper.rebuild_start(self.room.folder, entries, self.K)
        except MapperLost:
            raise
        except Exception:
            self._failed()
            return
        self.rebuilding = wanted
        self._rebuild_poses = dict(entries)
        self._t0 = time.perf_counter()

    def step(
        self, occupancy: Callable[[], tuple[float, np.ndarray] | None], on_rebuilt: OnRebuilt
    ) -> None:
        """A few more keyframes into the new map; when none are left, the swap, and
        ``on_rebuilt`` with what the drone's ``occupancy`` request asked for."""
        try:
            left = self.mapper.rebuild_step(self.cfg.rebuild_keyframes_per_step)
            if left == 0:
                self._finish(self.mapper.rebuild_finish(occupancy()), on_rebuilt)
        except MapperLost:
            raise
        except Exception:
            self._failed()

    def _finish(self, rebuilt: Rebuilt, on_rebuilt: OnRebuilt) -> None:
        """The rebuilt map replaced the old one (in the mapper, at once)."""
        correction, self.rebuilding = self.rebuilding, None
        assert correction is not None
        ms = (time.perf_counter() - self._t0) * 1e3
        T_map = self.loops.worlds.delta(self._map_world, correction.world)
        self._map_world = correction.world
        self._map_poses, self._rebuild_poses = self._rebuild_poses, {}
        with self._lock:
            f = self._figures
            f.rebuilds += 1
            f.rebuilds_cpu_ms += rebuilt.cpu_ms
            f.map_behind_m = 0.0
            f.last_rebuild_ms = round(ms, 1)
            f.last_rebuild_cpu_ms = round(rebuilt.cpu_ms, 1)
            f.last_rebuild_keyframes = rebuilt.keyframes
        with self.counts.lock:
            self.counts.dirty = True
            seq = self.counts.last_seq_processed
        if rebuilt.stats:
            self.counts.map_stats = rebuilt.stats
        self.log.info(
            "map rebuilt from %d keyframes in %.0f ms (world %d)",
            rebuilt.keyframes,
            ms,
            correction.world,
        )
        try:
            on_rebuilt(rebuilt, T_map, seq)
        finally:
            self._handled()

    def _failed(self) -> None:
        """A rebuild failed (logged from the except block): counted; the map stays as it was
        (in the old world) and the session goes on."""
        self.log.exception("rebuilding the map after a loop closure failed")
        self.counts.failed("loops_failed")
        self.rebuilding = None
        self._handled()
        try:
            self.mapper.rebuild_cancel()
        except MapperLost:
            raise
        except Exception:
            self.log.exception("cancelling the rebuild failed")


def loop_figures(loops: LoopClosing | None, rebuilds: MapRebuilds | None) -> dict:
    """A session's ``loops`` in its status: the loop thread's counts (zeros without online
    loop closure) and the map's rebuilds."""
    figures: dict[str, float | bool | None] = {
        "enabled": loops is not None,
        "keyframes": 0,
        "queued": 0,
        "found": 0,
        "refused": 0,
        "corrections": 0,
        "last_optimise_ms": None,
        "last_optimise_cpu_ms": None,
        "lookup_cpu_ms": None,
    }
    if loops is not None:
        figures.update(loops.figures())
    figures.update(RebuildFigures().as_dict() if rebuilds is None else rebuilds.figures())
    return figures
