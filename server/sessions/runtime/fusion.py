"""A live session's mapping thread: fuses the frames the tracking thread hands it into the map (in
the mapper: server/sessions/processes/mapper.py), sends the map's preview, feeds the drone's map,
writes the room's keyframes and hands them to the loop closer, runs the map's rebuilds after a loop
closure and triggers the periodic snapshots, so that none of it ever delays a pose."""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from server.geometry import Intrinsics
from server.mapping.config import MappingConfig
from server.registration.config import RegistrationConfig
from server.registration.preprocess import clean_depth
from server.sessions.processes.mapper import Mapper, MapperClient, MapperLost, Rebuilt
from server.sessions.processes.priority import MAPPING_NICE, lower_this_threads_priority
from server.sessions.runtime.counts import SessionCounts
from server.sessions.runtime.flight import Flight
from server.sessions.runtime.loop_closing import LoopClosing, LoopKeyframe
from server.sessions.runtime.rebuilds import MapRebuilds
from server.sessions.runtime.room_writer import RoomWriter
from server.sessions.updates import MapUpdate, Update

_KEYFRAME_WAIT_S = 10.0  # a keyframe waits this long for room in a mapper that is behind
_POLL_S = 0.2  # how often a wait on the mapping thread checks that it is still alive


@dataclass
class FuseJob:
    seq: int
    colour: np.ndarray
    depth: np.ndarray
    T_world_camera: np.ndarray
    keyframe: bool
    keyframe_id: int = -1  # the tracker's id of the keyframe, when ``keyframe``
    world: int = 0  # the corrected world (loop closure) T_world_camera is in (0: none yet)


class FuseJobs:
    """The fusion jobs waiting for the mapping thread, at most ``size`` (and the end, None,
    after them)."""

    def __init__(self, size: int) -> None:
        self._items: deque[FuseJob | None] = deque()
        self._size = size
        self._cond = threading.Condition()

    def put(self, job: FuseJob, wait_s: float) -> tuple[bool, FuseJob | None]:
        """Queue ``job`` when there is room, waiting up to ``wait_s``; a keyframe finding none
        takes the place of the oldest waiting job that is not a keyframe. Returns (queued, the
        job it replaced or None)."""
        with self._cond:
            evicted = None
            if len(self._items) >= self._size and job.keyframe:
                plain = (i for i, w in enumerate(self._items) if w is not None and not w.keyframe)
                if (i := next(plain, None)) is not None:
                    evicted = self._items[i]
                    del self._items[i]  # by place: FuseJob's == would compare images
            if not self._cond.wait_for(lambda: len(self._items) < self._size, wait_s):
                return False, None
            self._items.append(job)
            self._cond.notify_all()
            return True, evicted

    def get(self, timeout_s: float) -> FuseJob | None:
        """The oldest job (None: the end); raises queue.Empty after ``timeout_s``."""
        with self._cond:
            if not self._cond.wait_for(lambda: bool(self._items), timeout_s):
                raise queue.Empty
            job = self._items.popleft()
            self._cond.notify_all()
            return job

    def close(self) -> None:
        """The end, after the jobs queued."""
        with self._cond:
            self._items.append(None)
            self._cond.notify_all()


class SessionFusion:
    """The mapping thread (``start``): fuses each queued FuseJob (``queue``) with the mapper,
    at a lower priority than tracking. Keyframes are always fused; other frames are skipped
    when it is behind. A fusion that fails is counted and skipped; when the thread itself ends
    on an error, or the map's process is gone, ``fail`` ends the session.

    room: writes each fused keyframe into the session's room (None: rooms are not kept);
    loops, rebuilds: online loop closure (each written keyframe goes to the loop thread; the
    map is rebuilt after a correction), or None; snapshot_if_due: the periodic snapshot;
    failed: whether the session has failed (nothing waits for this thread then)."""

    def __init__(
        self,
        mapper: Mapper | MapperClient,
        K: Intrinsics,
        cfg: MappingConfig,
        registration: RegistrationConfig,
        counts: SessionCounts,
        publish: Callable[[Update], None],
        log: logging.LoggerAdapter,
        name: str,
        flight: Flight | None,
        room: RoomWriter | None,
        loops: LoopClosing | None,
        rebuilds: MapRebuilds | None,
        snapshot_if_due: Callable[[], None],
        fail: Callable[[str], None],
        failed: Callable[[], bool],
    ) -> None:
        self.mapper = mapper
        self.K = K
        self.cfg = cfg
        self.registration = registration
        self.counts = counts
        self.publish = publish
        self.log = log
        self.flight = flight
        self.room = room
        self.loops = loops
        self.rebuilds = rebuilds
        self.snapshot_if_due = snapshot_if_due
        self.fail = fail
        self.failed = failed
        self._jobs = FuseJobs(4)
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._merged: deque[FuseJob] = deque()  # a merged segment's keyframes (under the lock)
        self._lock = threading.Lock()
        # Mapping thread only: frames fused so far, how many of them the drone's map has been
        # asked to include, and when it last was.
        self._fused = 0
        self._surface_sent = False  # what the last MapUpdate said of the map's surface
        self._flight_map_at = -np.inf

    # ------------------------------------------------------------------ the tracking thread's
    def start(self) -> None:
        self._thread.start()

    def alive(self) -> bool:
        return self._thread.is_alive() and not self.failed()

    def queue(self, job: FuseJob) -> bool:
        """Frames are skipped when the mapper is behind; a keyframe is never lost from the map:
        it takes the place of the oldest waiting frame that is not one (skipped then), and
        waits for room, up to _KEYFRAME_WAIT_S, only when every waiting job is a keyframe.
        Before, it waited behind plain frames for a mapper that, niced, gets little CPU while
        the cores are busy: a second's stall of tracking, measured at 8 phones on 2 cores.
        Nothing waits for a mapping thread that has ended. True when queued: the frame, counted
        in ``counts.fusion_waiting`` by the caller, is counted off once fused; False when
        skipped (the caller counts it off)."""
        deadline = time.monotonic() + (_KEYFRAME_WAIT_S if job.keyframe else 0.0)
        while self.alive():
            queued, evicted = self._jobs.put(job, _POLL_S if job.keyframe else 0.0)
            if evicted is not None:  # counted in fusion_waiting, never to be fused
                with self.counts.lock:
                    self.counts.fusion_skipped += 1
                self.counts.fusion_settled()
            if queued:
                return True
            if time.monotonic() >= deadline:
                break
        with self.counts.lock:
            self.counts.fusion_skipped += 1
        return False

    def add_merged(self, jobs: list[FuseJob]) -> None:
        """A segment merged into the map: its kept keyframes, fused one between live frames
        (counted in ``counts.fusion_waiting`` until then)."""
        with self.counts.lock:
            self.counts.fusion_waiting += len(jobs)
        with self._lock:
            self._merged.extend(jobs)

    def end(self, timeout_s: float = 60.0) -> None:
        """After every queued fusion: the thread ends at the None (a dead one is not waited
        for)."""
        if self._thread.ident is None:  # never started
            return
        self._jobs.close()
        self._thread.join(timeout_s)

    # ------------------------------------------------------------------ the mapping thread
    def _run(self) -> None:
        """Runs at a lower priority than tracking (Linux nice values are per thread): when the
        cores are short, the map falls behind, not the poses."""
        lower_this_threads_priority(MAPPING_NICE)
        try:
            self._fuse_until_stopped()
        except MapperLost as exc:
            self.fail(f"the session's mapping process died{exc.why}")
        except BaseException as exc:  # the thread ends here: say why, and end the session
            self.log.exception("the mapping thread died")
            self.fail(f"the session's mapping thread died ({type(exc).__name__}: {exc})")

    def _fuse_until_stopped(self) -> None:
        rebuilds = self.rebuilds
        while True:
            if rebuilds is not None:
                rebuilds.start_if_wanted()
            merged = self._next_merged()
            if merged is not None:  # a merged segment's keyframes, one between live frames
                fused = self._fuse(merged)
                with self.counts.lock:
                    self.counts.recovery["segment_frames_fused"] += fused
                    self.counts.fusion_waiting -= 1
            rebuilding = rebuilds is not None and rebuilds.rebuilding is not None
            try:
                # A rebuild, or a merged segment's keyframes, go on between fusions: no long
                # wait for a job then.
                busy = rebuilding or merged is not None
                job = self._jobs.get(0.02 if busy else 1.0)
            except queue.Empty:
                if rebuilding:
                    self._rebuild_step()
                    continue
                self.snapshot_if_due()
                self._catch_up_flight_map()
                continue
            if job is None:  # stopping: the session writes the final snapshot itself
                self._finish_loops()
                return
            self._fuse(job)
            self.counts.fusion_settled()  # after the map's figures took it (``_fuse``)
            if rebuilds is not None and rebuilds.rebuilding is not None:
                self._rebuild_step()

    def _next_merged(self) -> FuseJob | None:
        with self._lock:
            return self._merged.popleft() if self._merged else None

    def _fuse(self, job: FuseJob) -> bool:
        """Fuse one job (and, during a rebuild, a keyframe into the new map too); False when
        the fusion failed (counted)."""
        self.snapshot_if_due()
        occupancy = self._occupancy_request()
        rebuild_pose = None
        if job.keyframe and self.rebuilds is not None:
            rebuild_pose = self.rebuilds.pose_in_rebuild(
                job.keyframe_id, job.T_world_camera, job.world
            )
        try:
            fused = self.mapper.fuse(
                job.colour, job.depth, self.K, job.T_world_camera, occupancy, rebuild_pose
            )
        except MapperLost:
            raise
        except Exception:
            self.log.exception("fusing frame %d failed", job.seq)
            self.counts.failed("fusions_failed")
            return False
        self._fused += 1
        if job.keyframe and self.rebuilds is not None:  # only corrections read it
            self.rebuilds.keyframe_fused(job.keyframe_id, job.T_world_camera)
        if job.keyframe and self.room is not None:
            self._keep_for_room(job, self.room)
        self.counts.changed()
        if fused.stats:
            self.counts.map_stats = fused.stats
        if len(fused.points) or fused.surface != self._surface_sent:
            self._surface_sent = fused.surface
            self.publish(
                MapUpdate(
                    job.seq, fused.points, fused.colours, fused.total_points, surface=fused.surface
                )
            )
        if occupancy is not None:
            self._update_flight_map(f"frame {job.seq}", fused.occupancy, fused.occupancy_error)
        return True

    def _keep_for_room(self, job: FuseJob, room: RoomWriter) -> None:
        """The keyframe into the room folder, and then to the loop thread (its features are
        computed already)."""
        kf = room.keep(
            job.keyframe_id, job.seq, job.T_world_camera, job.colour, job.depth, self.K, job.world
        )
        if kf is not None and self.loops is not None:
            depth = clean_depth(kf.depth, self.registration.depth)
            self.loops.submit(
                LoopKeyframe(kf.id, kf.frame_index, kf.T_world_keyframe, job.world, kf.place, depth)
            )

    # ------------------------------------------------------------------ rebuilds
    def _rebuild_step(self) -> None:
        assert self.rebuilds is not None
        self.rebuilds.step(lambda: self._occupancy_request(now=True), self._rebuilt)

    def _rebuilt(self, rebuilt: Rebuilt, T_map: np.ndarray, seq: int) -> None:
        """The rebuilt map replaced the old one: the preview restarts from it (a MapUpdate
        with reset), and the drone's map is its whole grid, the drone moving with the world
        (``Flight.map_replaced``)."""
        self._surface_sent = rebuilt.surface
        self.publish(
            MapUpdate(
                seq,
                rebuilt.points,
                rebuilt.colours,
                rebuilt.total_points,
                reset=True,
                surface=rebuilt.surface,
            )
        )
        if self.flight is None:
            return
        error = rebuilt.occupancy_error
        if error is None and rebuilt.occupancy is not None:
            try:
                self.flight.map_replaced(*rebuilt.occupancy, T_map, frames=self._fused)
            except Exception as exc:
                error = f"{type(exc).__name__}: {exc}"
        if error is not None:
            self.log.error("the drone's map missed the rebuilt map (%s)", error)
            self.counts.failed("flight_map_failed")

    def _finish_loops(self) -> None:
        """The session stops (after the last fusion): the loop thread takes the keyframes
        still queued, and the map is rebuilt for the last correction, so that the final
        snapshot and the room hold the corrected map and poses."""
        if self.loops is None or self.rebuilds is None:
            return
        self.loops.stop()
        self.rebuilds.start_if_wanted()
        while self.rebuilds.rebuilding is not None:
            self._rebuild_step()

    # ------------------------------------------------------------------ the drone's map
    def _catch_up_flight_map(self) -> None:
        """No frame to fuse (the phone holds still, or the stream ended): hand the drone the
        occupancy of the frames fused since its last update. Those frames asked for none (one
        is asked for at most every flight_map_interval_s), so without this the drone would
        refuse to fly into space they saw free until the next frame came. Asked for even when
        this session fused nothing since: in a shared room another phone's frames change the
        map (server/sessions/processes/room_map.py); the mapper answers None at once when
        nothing did."""
        if self.flight is None:
            return
        request = self._occupancy_request()
        if request is None:
            return
        try:
            grid, error = self.mapper.occupancy(*request), None
        except MapperLost:
            raise
        except Exception as exc:
            grid, error = None, f"{type(exc).__name__}: {exc}"
        self._update_flight_map("the catch-up", grid, error)

    def _update_flight_map(
        self,
        what: str,
        grid: tuple[np.ndarray, np.ndarray, np.ndarray] | None,
        error: str | None,
    ) -> None:
        """Hand the drone the occupancy the mapper gave for what changed (None: nothing did);
        the flight map then holds every frame fused so far. A failure is counted (the drone
        flies on the map it had) and never ends the mapping."""
        if error is None and self.flight is not None:
            try:
                if grid is not None:
                    self.flight.map_region_changed(*grid, frames=self._fused)
                else:
                    self.flight.map_includes(self._fused)
            except Exception as exc:
                error = f"{type(exc).__name__}: {exc}"
        if error is not None:
            self.log.error("the drone's map missed %s (%s)", what, error)
            self.counts.failed("flight_map_failed")

    def _occupancy_request(self, now: bool = False) -> tuple[float, np.ndarray] | None:
        """Ask the mapper for the drone's occupancy at most every flight_map_interval_s: a fused
        frame's changes span most of the room (its carved free space reaches the far walls),
        so feeding every frame would cost more than this, measured in
        benchmarks/flight_map_update.py. ``now``: whatever the interval (a rebuilt map)."""
        if self.flight is None or (
            not now and time.monotonic() - self._flight_map_at < self.cfg.flight_map_interval_s
        ):
            return None
        self._flight_map_at = time.monotonic()
        return self.flight.config.voxel_m, self.flight.R_flight_world
