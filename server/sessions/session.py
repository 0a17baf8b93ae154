"""One session: a worker thread that registers the newest frame, fuses the map and reports poses.

Frames arrive faster than they can be processed on a busy server; the inbox holds one frame and
the newest wins, so latency stays bounded and stale frames are dropped and counted.
"""

from __future__ import annotations

import logging
import os
import queue
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from server.atomic import atomic_write_bytes
from server.evaluation.trajectory import Trajectory, write_tum
from server.geometry import Intrinsics
from server.mapping.tsdf import MapError
from server.registration import Tracker, TrackingState, TrackResult
from server.registration.calibration import ColourToDepth
from server.registration.preprocess import clean_depth, resample_depth
from server.registration.relocalise import SegmentFrames
from server.rooms.continuation import RoomTracker
from server.rooms.room import (
    MAP_FILE,
    RoomError,
    link_keyframes,
    load_room,
    room_keyframe,
    write_keyframe,
    write_room_meta,
)
from server.sessions.config import SessionConfig
from server.sessions.course import BEST_FILE as COURSE_BEST_FILE
from server.sessions.errors import CommandRefused, SessionError, SnapshotError
from server.sessions.failures import Failures, SessionLog
from server.sessions.flight import Flight
from server.sessions.flight_log import FlightLog
from server.sessions.loop_closing import Correction, LoopClosing, LoopKeyframe, pose_move_m
from server.sessions.mapping import Mapper, MapperClient, MapperLost, Rebuilt
from server.sessions.priority import MAPPING_NICE, lower_this_threads_priority
from server.sessions.store import SessionStore, StoreError
from server.sessions.updates import (
    FrameData,
    FrameRefused,
    MapCorrected,
    MapUpdate,
    PoseUpdate,
    SessionFailed,
    Update,
)

log = logging.getLogger(__name__)

ROOM_FOLDER = "room"  # in a session's folder: the room it leaves (server/rooms/room.py)
_KEYFRAME_WAIT_S = 10.0  # a keyframe waits this long for room in a mapper that is behind
_POLL_S = 0.2  # how often a wait on the mapping thread checks that it is still alive


@dataclass
class _FuseJob:
    seq: int
    colour: np.ndarray
    depth: np.ndarray
    T_world_camera: np.ndarray
    keyframe: bool
    keyframe_id: int = -1  # the tracker's id of the keyframe, when ``keyframe``
    world: int = 0  # the corrected world (loop closure) T_world_camera is in (0: none yet)


class Session:
    """A live session. ``start`` launches its two workers; ``submit`` hands in frames.

    The tracking worker registers the newest frame and reports its pose at once; the mapping
    worker fuses frames into the TSDF behind it, so fusion never delays a pose. Keyframes are
    always fused; other frames are skipped when the mapper is behind. ``on_update`` receives
    PoseUpdate, MapUpdate, DroneUpdate and DroneNotice objects, from the worker threads.

    Failures are counted (``failures``, in the status and every pose) and logged with the
    session's id. A frame the tracker fails on is answered internal_error; a fusion that fails
    is skipped. When the map itself is gone (its process or thread died) the session fails as a
    whole (``fail``): frames are refused from then on and the client is told (SessionFailed);
    tracking never waits for a dead mapper, and ``stop`` never blocks on one."""

    def __init__(
        self,
        session_id: str,
        token_hash: str,
        store: SessionStore,
        config: SessionConfig | None = None,
        created_at: float | None = None,
        mapper: Mapper | MapperClient | None = None,
        room_dir: Path | None = None,
        loops_conn=None,
    ) -> None:
        """room_dir: a saved room (server/rooms/) to continue in: the tracker relocalises the
        first frames in it and the map starts as the room's; None starts an empty world.
        loops_conn: a pipe to a loop process (server/sessions/loop_process.py) for the loop
        closer, when this session closes loops; None closes them in a thread of this process."""
        self.id = session_id
        self.log = SessionLog(log, session_id)
        self.token_hash = token_hash
        self.store = store
        self.config = config or SessionConfig.from_config()
        self.created_at = created_at or time.time()
        self.closed = False
        self.client_name = ""
        self.intrinsics: Intrinsics | None = None
        # The first hello's gravity (unit, the first camera's axes): the drone's and an upright
        # mesh's down (server/mapping/upright.py); None when the client measured none.
        self.gravity: list[float] | None = None
        self.tracker: Tracker | RoomTracker | None = None
        self._colour_to_depth: ColourToDepth | None = None  # from the first frame on
        self.room_dir = room_dir
        # This session's room (server/rooms/): the keyframes written so far into its folder's
        # room/ (mapping thread), as (id, frame seq, T_world_keyframe), after the room it
        # continues in, if any.
        self._room_keyframes: list[tuple[int, int, np.ndarray]] = []
        # The corrected world (loop closure) each of those poses is in (guarded by _lock).
        self._room_worlds: dict[int, int] = {}
        self._room_sessions: list[dict] = []
        self._room_base_ids: list[int] = []  # the keyframes of the room continued in
        self._placed = False  # a frame has been tracked (in a room: recognised in it)
        # The map, in a process of its own when given one (server/sessions/mapping.py says why).
        self.mapper = mapper or Mapper(self.config.mapping)
        self._map_stats: dict = {}
        self._map_closed = False
        self.on_update: Callable[[Update], None] | None = None
        self.flight: Flight | None = None  # the drone, from the first hello on
        self.flight_log: FlightLog | None = None  # its flights, recorded and saved
        self._flight_map_at = -np.inf
        # Frames fused so far, and how many of them the drone's map has been asked to include
        # (both mapping thread only).
        self._fused = 0
        self._flight_map_fused = 0
        self._fuse_jobs: queue.Queue[_FuseJob | None] = queue.Queue(maxsize=4)
        self._mapping_thread: threading.Thread | None = None
        self.fusion_skipped = 0
        self.repeated = 0  # frames held at the pose before: a repeated colour or depth image
        self.last_seen = time.monotonic()
        self._trajectory: list[tuple[float, np.ndarray]] = []
        self._states = {s.value: 0 for s in TrackingState}
        self.received = self.processed = self.dropped = 0
        # Frames that carried the device's own pose, and those whose guess started from it.
        self._device_pose = {"frames": 0, "guesses": 0, "world_changes": 0}
        self._device_world = 0  # the last frame's device_world
        self._recovery = {
            "relocalised": 0,
            "segments": 0,
            "merged": 0,
            "in_segment": 0,
            "segment_frames_fused": 0,
        }
        # The current segment's keyframes kept for the map (tracking thread), and those of
        # merged segments that wait for the mapping thread (under the lock).
        self._segment_jobs: SegmentFrames[_FuseJob] = SegmentFrames(
            self.config.registration.relocalise.segment_keyframes_kept
        )
        self._merged_jobs: deque[_FuseJob] = deque()
        self.failures = Failures()  # guarded by _lock; flight_errors is the drone's own count
        self.failure: str | None = None  # why the session could not go on (see fail)
        self._last_seq = -1
        self._lock = threading.Lock()  # guards the trajectory and counters
        self._inbox: FrameData | None = None
        self._busy = False  # the worker holds a frame
        self._wake = threading.Condition()
        self._stopping = False
        self._worker: threading.Thread | None = None
        self._dirty = False
        self._last_snapshot = time.monotonic()
        self.snapshot_error: str | None = None  # why the latest snapshot failed, if it did
        # Online loop closure (server/sessions/loop_closing.py), from the first hello on when
        # configured. Corrections wait for the tracking thread in _corrections (under _wake)
        # and for the mapping thread in _rebuild_wanted (newest wins, under _lock).
        self.loops: LoopClosing | None = None
        self._loops_conn = loops_conn
        self._world = 0  # the corrected world the tracker is in (tracking thread)
        self._corrections: list[Correction] = []
        self._rebuild_wanted: Correction | None = None
        self._rebuilding: Correction | None = None  # mapping thread
        self._rebuild_t0 = 0.0
        self._map_world = 0  # the world the map and the drone's map are in (mapping thread)
        # Each room keyframe's pose in the map (fused there at it), and in the map a rebuild
        # in progress makes (mapping thread): what a correction's move is measured against.
        self._map_poses: dict[int, np.ndarray] = {}
        self._rebuild_poses: dict[int, np.ndarray] = {}
        self._rebuilds = 0
        self._rebuilds_skipped = 0
        self._rebuilds_cpu_ms = 0.0  # the mapping process's CPU over every rebuild so far
        self._map_behind_m = 0.0  # the most a keyframe moved since the map was fused, m
        self._last_rebuild: dict[str, float] = {}
        self._last_seq_processed = -1
        if room_dir is not None:
            self._inherit_course_best(room_dir)

    # ------------------------------------------------------------------ access
    def configure(
        self, intrinsics: Intrinsics, client_name: str = "", gravity: np.ndarray | None = None
    ) -> None:
        """Set the camera from the client's hello. A reconnecting client must present the same
        camera, as the map and trajectory were built with it. gravity: its direction in the
        first camera's frame (sets the drone's up; +y when None); a reconnect keeps the first."""
        if self.closed:
            raise SessionError("session_closed", "this session is closed; create a new one")
        if self.intrinsics is not None and self.intrinsics != intrinsics:
            raise SessionError(
                "intrinsics_changed",
                "this session was started with another camera; create a new session",
            )
        if self.tracker is None:
            self.tracker = self._make_tracker(intrinsics)
            if self.loops_wanted:
                self.loops = LoopClosing(
                    intrinsics,
                    self.config.registration,
                    self._loop_corrected,
                    self._loop_failed,
                    name=f"loops-{self.id}",
                    conn=self._loops_conn,
                )
        if self.flight is None and self.config.simulation is not None:
            self.flight = Flight(
                self.config.simulation,
                intrinsics,
                gravity,
                self._publish,
                self.config.drone_state_hz,
                log=SessionLog(logging.getLogger("server.sessions.flight"), self.id),
            )
            self.flight_log = FlightLog(
                self.store,
                self.id,
                self.config.drone_state_hz,
                self.config.flight_max_s,
                self.config.flights_kept,
            )
            self.flight.recorder = self.flight_log.recorder
            self.flight.course.best_path = self._course_best_path()
        if self.intrinsics is None and gravity is not None:  # a reconnect keeps the first
            g = np.asarray(gravity, dtype=np.float64)
            self.gravity = [float(v) for v in g / np.linalg.norm(g)]
        self.intrinsics = intrinsics
        self.client_name = client_name
        self.last_seen = time.monotonic()
        with self._lock:  # a new connection numbers its frames afresh (a reloaded page)
            self._last_seq = -1

    def _make_tracker(self, intrinsics: Intrinsics) -> Tracker | RoomTracker:
        """A tracker from the origin, or one that starts in the room and a map that starts as
        the room's (the drone's map is fed from it with the first fused frame)."""
        if self.room_dir is None:
            return Tracker(intrinsics, self.config.registration)
        try:
            room = load_room(self.room_dir, self.config.registration)
            tracker = RoomTracker(room, intrinsics, self.config.registration)
        except RoomError as exc:
            raise SessionError("room_unusable", str(exc)) from exc
        self.mapper.load(str(self.room_dir / MAP_FILE))
        self._room_keyframes = [(k.id, k.frame_index, k.T_world_keyframe) for k in room.keyframes]
        self._room_base_ids = [k.id for k in room.keyframes]
        self._room_sessions = list(room.sessions)
        self.log.info("continues in the room %s (%d keyframes)", self.room_dir, len(room.keyframes))
        return tracker

    def _inherit_course_best(self, room_dir: Path) -> None:
        """The best course runs flown in the room so far become this session's best list to
        beat (pilots compete per room, not per visit); a room without any starts empty."""
        source = room_dir / COURSE_BEST_FILE
        target = self._course_best_path()
        if target is None or not source.is_file() or target.exists():
            return
        try:
            target.parent.mkdir(parents=True, exist_ok=True)
            atomic_write_bytes(target, source.read_bytes())
        except OSError:
            self.log.exception("the room's course best list could not be carried over")
            with self._lock:
                self.failures.snapshots_failed += 1

    @property
    def loops_wanted(self) -> bool:
        """Online loop closure runs here (``SessionConfig.closes_loops``)."""
        return self.config.closes_loops(in_room=self.room_dir is not None)

    def _course_best_path(self) -> Path | None:
        """Where the drone's course results are kept (None: an id the store cannot hold)."""
        try:
            return self.store.file(self.id, COURSE_BEST_FILE)
        except StoreError:
            return None

    def _publish(self, update: Update) -> None:
        on_update = self.on_update
        if on_update is not None:
            on_update(update)

    def command(self, name: str, command_id: int, **fields) -> None:
        """A pilot command for the drone (see ``Flight.command``); raises CommandRefused."""
        if self.flight is None:
            raise CommandRefused(
                "bad_command",
                "no drone in this session: send a hello first"
                if self.config.simulation
                else "the drone simulation is off",
            )
        self.flight.command(name, command_id, **fields)

    # ------------------------------------------------------------------ frames in
    def start(self, on_update: Callable[[Update], None] | None = None) -> None:
        self.on_update = on_update
        if self.flight is not None:
            self.flight.start()
        if self._worker is None:
            self._worker = threading.Thread(target=self._run, name=f"track-{self.id}", daemon=True)
            self._mapping_thread = threading.Thread(
                target=self._map, name=f"map-{self.id}", daemon=True
            )
            self._worker.start()
            self._mapping_thread.start()
            if self.loops is not None:
                self.loops.start()

    def submit(self, frame: FrameData) -> None:
        """Queue a frame; a frame still waiting is dropped in its favour."""
        if self.tracker is None:
            raise SessionError("no_hello", "send a hello before frames")
        if self.failure is not None:
            raise SessionError("session_failed", f"{self.failure}; the session has ended")
        with self._lock:
            if frame.seq <= self._last_seq:
                raise SessionError(
                    "bad_sequence",
                    f"sequence number {frame.seq} is not above the last one ({self._last_seq})",
                )
            self._last_seq = frame.seq
            self.received += 1
        self.last_seen = time.monotonic()
        with self._wake:
            if self._inbox is not None:
                with self._lock:
                    self.dropped += 1
            self._inbox = frame
            self._wake.notify()

    def drain(self, timeout_s: float = 5.0) -> bool:
        """Wait until every submitted frame has been processed (or dropped); False on timeout.
        A client saying bye still gets the answers to the frames it sent."""
        deadline = time.monotonic() + timeout_s
        with self._wake:
            while self._inbox is not None or self._busy:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return False
                self._wake.wait(remaining)
        return True

    # ------------------------------------------------------------------ worker
    def _configured(self) -> tuple[Intrinsics, Tracker | RoomTracker]:
        """The camera and tracker the hello set (``configure``); submit takes no frame before."""
        if self.intrinsics is None or self.tracker is None:
            raise SessionError("no_hello", "send a hello before frames")
        return self.intrinsics, self.tracker

    def _run(self) -> None:
        while True:
            with self._wake:
                while self._inbox is None and not self._stopping and not self._corrections:
                    self._wake.wait()
                frame, self._inbox = self._inbox, None
                corrections, self._corrections = self._corrections, []
                self._busy = frame is not None
                stopping = self._stopping
            if corrections:  # between two frames: track never sees a half-corrected world
                self._apply_corrections(corrections)
            if frame is not None:
                try:
                    self._process(frame)
                except Exception as exc:  # one bad frame must not end the session's worker
                    self.frame_failed(frame.seq, exc)
                with self._wake:
                    self._busy = False
                    self._wake.notify_all()  # for drain()
            if stopping and frame is None:
                return

    # ------------------------------------------------------------------ loop closure
    def _loop_corrected(self, correction: Correction) -> None:
        """A verified loop corrected the world (loop thread): the tracker takes it between two
        frames, the mapping thread rebuilds the map (the newest correction wins)."""
        with self._lock:
            self._rebuild_wanted = correction
        with self._wake:
            self._corrections.append(correction)
            self._wake.notify()

    def _loop_failed(self, exc: BaseException) -> None:
        """The loop thread failed on a keyframe (logged from its except block): counted; the
        keyframe is left out of the graph and the session goes on."""
        self.log.error("loop closure failed on a keyframe", exc_info=exc)
        with self._lock:
            self.failures.loops_failed += 1

    def _apply_corrections(self, corrections: list[Correction]) -> None:
        """Move the tracker into each corrected world in turn (tracking thread, between two
        frames) and tell the client (map_corrected): poses already sent stay as they were;
        those of frames from ``from_seq`` on are in the corrected world."""
        tracker = self.tracker
        for c in corrections:
            if isinstance(tracker, Tracker):  # loops never run in a room (RoomTracker)
                try:
                    tracker.apply_correction(c.keyframes, c.T_correction)
                except Exception:
                    self.log.exception("correcting the tracker failed")
                    with self._lock:
                        self.failures.loops_failed += 1
                    continue
            self._world = c.world
            if self.flight is not None:  # the drone is shown in the corrected world at once
                self.flight.world_corrected(c.T_correction)
            with self._lock:
                from_seq = self._last_seq_processed + 1
            keyframes = [(i, c.seqs[i], T) for i, T in sorted(c.keyframes.items())]
            self._publish(MapCorrected(c.loops, from_seq, c.T_correction, keyframes, c.refused))

    def loop_figures(self) -> dict:
        """The status's ``loops``: the loop thread's counts and the map rebuilds."""
        figures: dict[str, float | bool | None] = {
            "enabled": self.loops is not None,
            "keyframes": 0,
            "queued": 0,
            "found": 0,
            "refused": 0,
            "corrections": 0,
            "last_optimise_ms": None,
            "last_optimise_cpu_ms": None,
            "lookup_cpu_ms": None,
        }
        if self.loops is not None:
            figures.update(self.loops.figures())
        with self._lock:
            figures["rebuilds"] = self._rebuilds
            figures["rebuilds_skipped"] = self._rebuilds_skipped
            figures["rebuilds_cpu_ms"] = round(self._rebuilds_cpu_ms, 1)
            figures["map_behind_m"] = round(self._map_behind_m, 4)
            figures["last_rebuild_ms"] = self._last_rebuild.get("ms")
            figures["last_rebuild_cpu_ms"] = self._last_rebuild.get("cpu_ms")
            figures["last_rebuild_keyframes"] = self._last_rebuild.get("keyframes")
        return figures

    def frame_failed(self, seq: int | None, exc: Exception, stage: str = "") -> None:
        """The server failed on frame ``seq`` (a bug, raised as ``exc``): logged with its
        traceback (call from the except block), counted, and answered internal_error."""
        self.log.exception("frame %s failed%s", seq, f" {stage}" if stage else "")
        with self._lock:
            self.failures.frames_failed += 1
        self._publish(
            FrameRefused(
                seq,
                "internal_error",
                f"the server failed on this frame ({type(exc).__name__}: {exc})",
            )
        )

    def _snapshot_if_due(self) -> None:
        """The periodic snapshot (mapping thread); a failure keeps everything in memory."""
        if not self._dirty or (
            time.monotonic() - self._last_snapshot < self.config.snapshot_interval_s
        ):
            return
        try:
            self.snapshot()
        except SnapshotError as exc:
            self.log.error("%s; the previous one stays whole and the map stays in memory", exc)

    def _count_recovery(self, result: TrackResult) -> None:
        """The status's ``recovery`` counts (call holding the lock)."""
        r = self._recovery
        r["relocalised"] += result.relocalised
        r["merged"] += result.merged is not None
        r["in_segment"] += result.recovery == "segment"
        r["segments"] = max(r["segments"], result.segment)  # numbered from 1 as they start

    def _process(self, frame: FrameData) -> None:
        """Track the frame and publish its pose at once; then the keyframe work the tracker
        deferred (a new keyframe, or a switch to an earlier one), and the frame's fusion job:
        the client never waits for either."""
        K, tracker = self._configured()
        t0, cpu0 = time.perf_counter(), time.thread_time()
        depth = resample_depth(frame.depth, K.width, K.height)
        # Unregistered colour (a raw Kinect-like sensor) resampled onto depth; as it is else.
        colour = (
            frame.colour
            if self._colour_to_depth is None
            else self._colour_to_depth(frame.colour, depth)
        )
        result = tracker.track(
            colour, depth, T_device_camera=frame.T_device_camera, device_world=frame.device_world
        )
        if result is None:  # in a room, before a frame is recognised in it: no pose yet
            result = _not_placed(frame.seq)
        timings = {
            "decode": frame.decode_ms,
            **{f"track_{k}": v for k, v in result.timings_ms.items()},
        }
        # This thread's own CPU time: track minus track_cpu is time spent waiting for a core
        # (or the GIL), which tells a busy machine from slow registration. Read inside the wall
        # interval, so that it never exceeds it.
        timings["track_cpu"] = (time.thread_time() - cpu0) * 1e3
        timings["track"] = (time.perf_counter() - t0) * 1e3
        tracked = result.state is not TrackingState.LOST
        if self.flight is not None and tracked:  # before the pose: a tap may name this frame
            self.flight.camera_moved(frame.seq, result.T_world_camera, depth)
        with self._lock:
            self._trajectory.append((frame.timestamp, result.T_world_camera))
            self._last_seq_processed = frame.seq
            self.processed += 1
            self._states[result.state.value] += 1
            self.repeated += result.repeated is not None
            self._device_pose["frames"] += frame.T_device_camera is not None
            self._device_pose["guesses"] += result.prior_used
            self._device_pose["world_changes"] += frame.device_world != self._device_world
            self._device_world = frame.device_world
            self._count_recovery(result)
            dropped, processed = self.dropped, self.processed
            self._dirty = True
        timings["server_total"] = (time.monotonic() - frame.received_at) * 1e3
        self._publish(
            PoseUpdate(
                frame.seq,
                frame.timestamp,
                result.T_world_camera,
                result.state.value,
                result.inliers,
                result.new_keyframe or result.keyframe_due,
                timings,
                dropped,
                processed,
                self.failure_counts(),
                result.recovery,
            )
        )
        new_keyframe = result.new_keyframe
        if result.keyframe_due:
            new_keyframe = tracker.update_keyframe()
        if result.recovery == "segment" and new_keyframe:
            job = _FuseJob(frame.seq, colour, depth, result.T_world_camera, False)
            self._segment_jobs.keep(result.segment, job, result.T_world_camera)
        elif result.merged is not None:
            self._fuse_merged_segment(*result.merged)
        # The first frame placed in a room is always fused: with it the drone's map is fed the
        # room's map (a fresh session's first frame is its first keyframe anyway).
        first_placed = tracked and not self._placed
        self._placed = self._placed or tracked
        if result.fusable and (
            new_keyframe or first_placed or (processed - 1) % self.config.mapping.fuse_every == 0
        ):
            self._queue_fusion(
                _FuseJob(
                    frame.seq,
                    colour,
                    depth,
                    result.T_world_camera,
                    new_keyframe,
                    result.keyframe_id,
                    self._world,
                )
            )

    # ------------------------------------------------------------------ mapping worker
    def _fuse_merged_segment(self, segment: int, T_correction: np.ndarray) -> None:
        """A segment merged into the map: its kept keyframes move with it and go to the mapping
        thread, which fuses them (and feeds the drone's map) between the live frames."""
        jobs = []
        for job, T_world_camera in self._segment_jobs.merged(segment, T_correction):
            job.T_world_camera, job.world = T_world_camera, self._world
            jobs.append(job)
        with self._lock:
            self._merged_jobs.extend(jobs)

    def _next_merged_job(self) -> _FuseJob | None:
        with self._lock:
            return self._merged_jobs.popleft() if self._merged_jobs else None

    def _queue_fusion(self, job: _FuseJob) -> None:
        """Keyframes wait for room (no keyframe is lost from the map), up to _KEYFRAME_WAIT_S;
        other frames are skipped when the mapper is behind. Nothing waits for a mapping thread
        that has ended."""
        deadline = time.monotonic() + (_KEYFRAME_WAIT_S if job.keyframe else 0.0)
        while self._mapping_alive():
            try:
                if job.keyframe:
                    self._fuse_jobs.put(job, timeout=_POLL_S)
                else:
                    self._fuse_jobs.put_nowait(job)
                return
            except queue.Full:
                if time.monotonic() >= deadline:
                    break
        with self._lock:
            self.fusion_skipped += 1

    def _mapping_alive(self) -> bool:
        thread = self._mapping_thread
        return thread is not None and thread.is_alive() and self.failure is None

    def _map(self) -> None:
        """The mapping thread: fuses frames and writes the periodic snapshots, so that a slow
        disk delays the map, never a pose. It runs at a lower priority than tracking (Linux nice
        values are per thread): when the cores are short, the map falls behind, not the poses.
        A fusion that fails is counted and skipped; if the thread itself ends on an error, or
        the map's process is gone, the session cannot go on (``fail``)."""
        lower_this_threads_priority(MAPPING_NICE)
        try:
            self._fuse_until_stopped()
        except MapperLost:
            self.fail("the session's mapping process died")
        except BaseException as exc:  # the thread ends here: say why, and end the session
            self.log.exception("the mapping thread died")
            self.fail(f"the session's mapping thread died ({type(exc).__name__}: {exc})")

    def _fuse_until_stopped(self) -> None:
        while True:
            self._start_rebuild_if_wanted()
            merged = self._next_merged_job()
            if merged is not None:  # a merged segment's keyframes, one between live frames
                if self._fuse(merged):
                    with self._lock:
                        self._recovery["segment_frames_fused"] += 1
            try:
                # A rebuild, or a merged segment's keyframes, go on between fusions: no long
                # wait for a job then.
                busy = self._rebuilding is not None or merged is not None
                job = self._fuse_jobs.get(timeout=0.02 if busy else 1.0)
            except queue.Empty:
                if self._rebuilding is not None:
                    self._rebuild_step()
                    continue
                self._snapshot_if_due()
                self._catch_up_flight_map()
                continue
            if job is None:  # stopping: stop() writes the final snapshot itself
                self._finish_loops()
                return
            self._fuse(job)
            if self._rebuilding is not None:
                self._rebuild_step()

    def _fuse(self, job: _FuseJob) -> bool:
        """Fuse one job (and, during a rebuild, a keyframe into the new map too); False when
        the fusion failed (counted)."""
        self._snapshot_if_due()
        K, _ = self._configured()  # a job comes from a tracked frame: after the hello
        occupancy = self._occupancy_request()
        rebuilding = self._rebuilding
        rebuild_pose = None
        if rebuilding is not None and job.keyframe and self.loops is not None:
            rebuild_pose = self.loops.worlds.carry(
                job.keyframe_id, job.T_world_camera, job.world, rebuilding.world
            )
            self._rebuild_poses[job.keyframe_id] = rebuild_pose
        try:
            fused = self.mapper.fuse(
                job.colour, job.depth, K, job.T_world_camera, occupancy, rebuild_pose
            )
        except MapperLost:
            raise
        except Exception:
            self.log.exception("fusing frame %d failed", job.seq)
            with self._lock:
                self.failures.fusions_failed += 1
            return False
        self._fused += 1
        if job.keyframe and self.loops is not None:  # only corrections read it
            self._map_poses[job.keyframe_id] = job.T_world_camera
        if job.keyframe and self.config.save_room:
            self._keep_room_keyframe(job, K)
        with self._lock:
            self._dirty = True
        if fused.stats:
            self._map_stats = fused.stats
        if len(fused.points):
            self._publish(MapUpdate(job.seq, fused.points, fused.colours, fused.total_points))
        if occupancy is not None:
            self._update_flight_map(f"frame {job.seq}", fused.occupancy, fused.occupancy_error)
        return True

    # ------------------------------------------------------------------ map rebuild
    def _start_rebuild_if_wanted(self) -> None:
        """Start rebuilding the map for the newest correction (mapping thread), from every
        keyframe written so far at its pose in the corrected world; the room's keyframe poses
        become these. A rebuild in progress finishes first (restarting it at every loop would
        never finish while the camera keeps closing loops); corrections that came meanwhile
        wait, and only the newest of them is rebuilt. A correction that moves no keyframe by
        more than ``mapping.rebuild_min_move_m`` from its pose in the map leaves the map as it
        is (counted as skipped): the moves add up until one is worth a rebuild."""
        if self._rebuilding is not None:
            return
        with self._lock:
            wanted, self._rebuild_wanted = self._rebuild_wanted, None
        if wanted is None or self.loops is None:
            return
        worlds = self.loops.worlds
        with self._lock:
            self._room_keyframes = [
                (i, seq, worlds.carry(i, T, self._room_worlds.get(i, 0), wanted.world))
                for i, seq, T in self._room_keyframes
            ]
            self._room_worlds = {i: wanted.world for i, _, _ in self._room_keyframes}
            entries = [(i, T) for i, _, T in self._room_keyframes]
        moves = [pose_move_m(self._map_poses[i], T) for i, T in entries if i in self._map_poses]
        move = max(moves, default=0.0)
        with self._lock:
            self._map_behind_m = move
        if move <= self.config.mapping.rebuild_min_move_m:
            with self._lock:
                self._rebuilds_skipped += 1
            self.log.info(
                "world %d moves the map by %.3f m at most: not re-fused", wanted.world, move
            )
            return
        K, _ = self._configured()
        try:
            self.mapper.rebuild_start(self.store.folder(self.id) / ROOM_FOLDER, entries, K)
        except MapperLost:
            raise
        except Exception:
            self._rebuild_failed()
            return
        self._rebuilding = wanted
        self._rebuild_poses = dict(entries)
        self._rebuild_t0 = time.perf_counter()

    def _rebuild_step(self) -> None:
        """A few more keyframes into the new map; when none are left, the swap."""
        try:
            left = self.mapper.rebuild_step(self.config.mapping.rebuild_keyframes_per_step)
            if left == 0:
                self._finish_rebuild(self.mapper.rebuild_finish(self._occupancy_request(True)))
        except MapperLost:
            raise
        except Exception:
            self._rebuild_failed()

    def _finish_rebuild(self, rebuilt: Rebuilt) -> None:
        """The rebuilt map replaced the old one (in the mapper, at once): the preview restarts
        from it (a MapUpdate with reset), and the drone's map is its whole grid, the drone
        moving with the world (``Flight.map_replaced``)."""
        correction, self._rebuilding = self._rebuilding, None
        assert correction is not None and self.loops is not None
        ms = (time.perf_counter() - self._rebuild_t0) * 1e3
        T_map = self.loops.worlds.delta(self._map_world, correction.world)
        self._map_world = correction.world
        self._map_poses, self._rebuild_poses = self._rebuild_poses, {}
        with self._lock:
            self._rebuilds += 1
            self._rebuilds_cpu_ms += rebuilt.cpu_ms
            self._map_behind_m = 0.0
            self._last_rebuild = {
                "ms": round(ms, 1),
                "cpu_ms": round(rebuilt.cpu_ms, 1),
                "keyframes": rebuilt.keyframes,
            }
            self._dirty = True
            seq = self._last_seq_processed
        if rebuilt.stats:
            self._map_stats = rebuilt.stats
        self.log.info(
            "map rebuilt from %d keyframes in %.0f ms (world %d)",
            rebuilt.keyframes,
            ms,
            correction.world,
        )
        self._publish(
            MapUpdate(seq, rebuilt.points, rebuilt.colours, rebuilt.total_points, reset=True)
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
            with self._lock:
                self.failures.flight_map_failed += 1
            return
        self._flight_map_fused = self._fused

    def _rebuild_failed(self) -> None:
        """A rebuild failed (logged from the except block): counted; the map stays as it was
        (in the old world) and the session goes on."""
        self.log.exception("rebuilding the map after a loop closure failed")
        with self._lock:
            self.failures.loops_failed += 1
        self._rebuilding = None
        try:
            self.mapper.rebuild_cancel()
        except MapperLost:
            raise
        except Exception:
            self.log.exception("cancelling the rebuild failed")

    def _finish_loops(self) -> None:
        """The session stops (mapping thread, after the last fusion): the loop thread takes the
        keyframes still queued, and the map is rebuilt for the last correction, so that the
        final snapshot and the room hold the corrected map and poses."""
        if self.loops is None:
            return
        self.loops.stop()
        self._start_rebuild_if_wanted()
        while self._rebuilding is not None:
            self._rebuild_step()

    def _keep_room_keyframe(self, job: _FuseJob, K: Intrinsics) -> None:
        """Write a keyframe into this session's room folder (mapping thread: its features and
        images cost 20-40 ms, which the poses do not wait for). A failure is counted; the
        session goes on without that keyframe in its room."""
        try:
            kf = room_keyframe(
                job.keyframe_id,
                job.seq,
                job.T_world_camera,
                job.colour,
                job.depth,
                K,
                self.config.registration,
            )
            write_keyframe(self.store.folder(self.id) / ROOM_FOLDER, kf)
        except Exception:
            self.log.exception("keeping keyframe %d for the room failed", job.keyframe_id)
            with self._lock:
                self.failures.room_keyframes_failed += 1
            return
        with self._lock:
            self._room_keyframes.append((kf.id, kf.frame_index, kf.T_world_keyframe))
            self._room_worlds[kf.id] = job.world
        if self.loops is not None:  # its features are computed already: the loop thread's
            self.loops.submit(
                LoopKeyframe(
                    kf.id,
                    kf.frame_index,
                    kf.T_world_keyframe,
                    job.world,
                    kf.place,
                    clean_depth(kf.depth, self.config.registration.depth),
                )
            )

    def save_room(self) -> bool:
        """Make this session's folder a room (``room/``: its keyframes, those of the room it
        continued in, and its final map) for a later session to continue in; False when it has
        no keyframe or no map. Call after the final snapshot."""
        folder = self.store.folder(self.id)
        with self._lock:
            keyframes = list(self._room_keyframes)
            worlds = dict(self._room_worlds)
        if self.loops is not None:  # each at its pose in the latest corrected world
            carry = self.loops.worlds.carry
            keyframes = [(i, f, carry(i, T, worlds.get(i, 0))) for i, f, T in keyframes]
        if (
            not self.config.save_room
            or self.intrinsics is None
            or not keyframes
            or not (folder / MAP_FILE).is_file()
        ):
            return False
        room = folder / ROOM_FOLDER
        room.mkdir(parents=True, exist_ok=True)
        if self.room_dir is not None:
            link_keyframes(self.room_dir, room, self._room_base_ids)
        (room / MAP_FILE).unlink(missing_ok=True)
        os.link(folder / MAP_FILE, room / MAP_FILE)
        best = self._course_best_path()  # the course results go with the room
        (room / COURSE_BEST_FILE).unlink(missing_ok=True)
        if best is not None and best.is_file():
            os.link(best, room / COURSE_BEST_FILE)
        sessions = [*self._room_sessions, {"session": self.id, "keyframes_after": len(keyframes)}]
        write_room_meta(room, self.intrinsics, keyframes, sessions)
        return True

    def _catch_up_flight_map(self) -> None:
        """No frame to fuse (the phone holds still, or the stream ended): hand the drone the
        occupancy of the frames fused since its last update. Those frames asked for none (one
        is asked for at most every flight_map_interval_s), so without this the drone would
        refuse to fly into space they saw free until the next frame came."""
        if self.flight is None or self._flight_map_fused == self._fused:
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
            with self._lock:
                self.failures.flight_map_failed += 1
            return
        self._flight_map_fused = self._fused

    def fail(self, reason: str) -> None:
        """The session cannot go on (its map is gone): frames are refused from now on, and the
        client is told (SessionFailed); the web side then stops and saves the session."""
        with self._lock:
            if self.failure is not None:
                return
            self.failure = reason
        self.log.error("%s; the session ends and is saved", reason)
        self._publish(SessionFailed(reason, saved=True))

    def _occupancy_request(self, now: bool = False) -> tuple[float, np.ndarray] | None:
        """Ask the mapper for the drone's occupancy at most every flight_map_interval_s: a fused
        frame's changes span most of the room (its carved free space reaches the far walls),
        so feeding every frame would cost more than this, measured in
        benchmarks/flight_map_update.py. ``now``: whatever the interval (a rebuilt map)."""
        if self.flight is None or (
            not now
            and time.monotonic() - self._flight_map_at < self.config.mapping.flight_map_interval_s
        ):
            return None
        self._flight_map_at = time.monotonic()
        return self.flight.config.voxel_m, self.flight.R_flight_world

    # ------------------------------------------------------------------ results
    def trajectory(self) -> Trajectory:
        with self._lock:
            stamps = np.array([t for t, _ in self._trajectory], dtype=np.float64)
            poses = np.array([T for _, T in self._trajectory]).reshape(-1, 4, 4)
        return Trajectory(stamps, poses)

    def failure_counts(self) -> dict[str, int]:
        """The session's Failures so far, by name (the drone counts its own flight errors)."""
        with self._lock:
            counts = self.failures.as_dict()
        if self.flight is not None:
            counts["flight_errors"] = self.flight.errors
        if self.flight_log is not None:  # a flight recording the disk refused
            counts["snapshots_failed"] += self.flight_log.saves_failed
        return counts

    def _map_figures(self, wait: bool = False) -> dict:
        """The map's statistics: fresh when the mapper is idle; while it fuses, as of the latest
        fusion (a status never waits behind the mapper, which runs at a lower priority and may
        take seconds on a loaded machine). Once its process has ended (stopped, or died), its
        last."""
        if not self._map_closed:
            try:
                fresh = self.mapper.stats(wait=wait or not self._map_stats)
            except MapperLost:
                self._map_closed = True
            else:
                if fresh is not None:
                    self._map_stats = fresh
        return self._map_stats

    def status(self) -> dict:
        map_stats = self._map_figures()
        failures = self.failure_counts()
        loops = self.loop_figures()
        with self._lock:
            return {
                "id": self.id,
                "created_at": self.created_at,
                "closed": self.closed,
                "client_name": self.client_name,
                "frames_received": self.received,
                "frames_processed": self.processed,
                "frames_dropped": self.dropped,
                "frames_failed": failures["frames_failed"],
                "fusion_skipped": self.fusion_skipped,
                "frames_repeated": self.repeated,
                "tracking_states": dict(self._states),
                "device_pose": dict(self._device_pose),
                "recovery": dict(self._recovery),
                "trajectory_poses": len(self._trajectory),
                "map": map_stats,
                "fusion_failed": failures["fusions_failed"],  # the name before failures existed
                "failures": failures,
                "failure": self.failure,
                "intrinsics": None if self.intrinsics is None else self.intrinsics.__dict__,
                "gravity": self.gravity,
                "drone": None if self.flight is None else self.flight.summary(),
                "snapshot_error": self.snapshot_error,
                "loops": loops,
            }

    def snapshot(self) -> None:
        """Write map, trajectory and meta as one snapshot: staged beside the previous one, then
        renamed into place (``SessionStore.commit``), so a crash leaves a whole snapshot. When
        the map's process is gone, its files stay as the previous snapshot left them.

        Raises SnapshotError when the disk refuses (full, gone): the previous snapshot stays
        whole, everything stays in memory, and ``snapshot_error`` (in the status) says why until
        a later snapshot succeeds."""
        with self._lock:
            self._dirty = False
        try:
            staging = self.store.staging(self.id)
            write_tum(staging / "trajectory.tum", self.trajectory())
            names = ["trajectory.tum"]
            if not self._map_closed:
                try:
                    names += self.mapper.save(str(staging))
                except MapperLost:
                    self._map_closed = True
            if self.flight_log is not None:  # the flight in progress, as far as it got
                self.flight_log.save_open()
            self.snapshot_error = None
            self.store.commit(self.id, names, self.meta())
        except (OSError, MapError) as exc:  # MapError: Open3D refused to write
            with self._lock:
                self._dirty = True
                self.failures.snapshots_failed += 1
            self.snapshot_error = f"{type(exc).__name__}: {exc}"
            raise SnapshotError(f"session {self.id}: snapshot failed ({exc})") from exc
        finally:
            self._last_snapshot = time.monotonic()  # a failed one is retried after the interval

    def meta(self) -> dict:
        meta = {
            "id": self.id,
            "token_sha256": self.token_hash,
            "created_at": self.created_at,
            "closed": self.closed,
            "voxel_m": self.config.mapping.tsdf.voxel_m,
            "status": self.status(),
        }
        if self.failure is not None:
            meta["failure"] = self.failure
        return meta

    def stop(self, save: bool = True) -> None:
        """Stop the worker after the frame in hand, then (optionally) write a final snapshot.
        Never waits for a mapping thread that has ended."""
        with self._wake:
            self._stopping = True
            self._wake.notify()
        if self.flight is not None:
            self.flight.stop()
        if self._worker is not None:
            self._worker.join(timeout=30)
            self._end_mapping_thread()
        if self.loops is not None:  # ended by the mapping thread, unless that one died
            self.loops.stop(timeout_s=10.0)
        if self.flight_log is not None:  # the flight in progress ends with the session
            self.flight_log.close()
        self.closed = True
        if save:
            self.snapshot()  # raises SnapshotError: the map stays, for the next try
            try:
                self.save_room()
            except OSError:
                self.log.exception("saving the session's room failed")
                with self._lock:
                    self.failures.room_keyframes_failed += 1
        self._map_figures(wait=True)
        self._map_closed = True
        self.mapper.close()

    def _end_mapping_thread(self, timeout_s: float = 60.0) -> None:
        """After every queued fusion: the thread ends at the None (a dead one is not waited
        for)."""
        thread = self._mapping_thread
        if thread is None:  # never started
            return
        deadline = time.monotonic() + timeout_s
        while thread.is_alive() and time.monotonic() < deadline:
            try:
                self._fuse_jobs.put(None, timeout=_POLL_S)
                break
            except queue.Full:
                continue
        thread.join(max(0.0, deadline - time.monotonic()))


def _not_placed(seq: int) -> TrackResult:
    """The answer for a frame of a session in a room before any frame was recognised in it:
    lost, at the identity (no pose is known yet)."""
    return TrackResult(seq, np.eye(4), TrackingState.LOST, 0, np.inf, 0.0, -1, False)
