"""One live session: the orchestrator of its parts, which run on threads of their own.

- tracking (server/sessions/runtime/tracking.py): the client's frames in order (``accept``),
  the newest through the frame step (server/frame_step.py), its pose published at once;
- fusion (server/sessions/runtime/fusion.py): the mapping thread, behind it: the map, its preview,
  the drone's map, the room's keyframes (server/sessions/runtime/room_writer.py), the periodic
  snapshots, and, with online loop closure (server/sessions/runtime/loop_closing.py), the map's
  rebuilds (server/sessions/runtime/rebuilds.py);
- the drone (server/sessions/runtime/flight.py), on its own thread.

The parts are made with the first hello, when the camera is known; this object wires them, and
answers for the session as a whole: status, snapshots, the end (the map's part in those:
server/sessions/runtime/session_map.py).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from server.evaluation.trajectory import Trajectory, write_tum
from server.geometry import Intrinsics
from server.registration import Tracker
from server.rooms.continuation import RoomTracker
from server.sessions.config import SessionConfig
from server.sessions.errors import CommandRefused, SessionError
from server.sessions.failures import SessionLog
from server.sessions.flight_store import FlightLog
from server.sessions.processes.mapper import Mapper, MapperClient
from server.sessions.runtime.counts import SessionCounts
from server.sessions.runtime.drone_setup import best_list_paths, inherit_best, make_flight
from server.sessions.runtime.flight import Flight
from server.sessions.runtime.fusion import SessionFusion
from server.sessions.runtime.loop_closing import Correction, LoopClosing
from server.sessions.runtime.rebuilds import MapRebuilds, loop_figures
from server.sessions.runtime.room_writer import ROOM_FOLDER as ROOM_FOLDER
from server.sessions.runtime.room_writer import RoomWriter, continued_room, track_and_keep
from server.sessions.runtime.session_map import SessionMap
from server.sessions.runtime.snapshots import Snapshots
from server.sessions.runtime.tracking import SessionTracking, live_step
from server.sessions.store import SessionStore
from server.sessions.updates import FrameData, FrameRefused, SessionFailed, Update

log = logging.getLogger(__name__)


class Session:
    """A live session. ``configure`` (the hello) makes its parts, ``start`` launches their
    threads, ``accept`` and ``submit`` hand in frames.

    The tracking thread registers the newest frame and reports its pose at once; the mapping
    thread fuses frames into the TSDF behind it, so fusion never delays a pose. Keyframes are
    always fused; other frames are skipped when the mapper is behind. ``on_update`` receives
    PoseUpdate, MapUpdate, DroneUpdate and DroneNotice objects, from the worker threads.

    Failures are counted (``failure_counts``, in the status and every pose) and logged with the
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
        map_shared: bool = False,
    ) -> None:
        """room_dir: a saved room (server/rooms/) to continue in: the tracker relocalises the
        first frames in it and the map starts as the room's; None starts an empty world.
        map_shared: ``mapper`` is a live shared room's map, whose owner snapshots it.
        loops_conn: a pipe to a loop process (server/sessions/processes/loop_process.py) for the
        loop closer, when this session closes loops; None closes them in a thread of this
        process."""
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
        self.room_dir = room_dir
        self.map_shared = map_shared
        # The map, in a process of its own when given one (processes/mapper.py says why).
        self.mapper = mapper or Mapper(self.config.mapping)
        self.counts = SessionCounts()  # failures, counters, the snapshot's dirty flag
        self.map = SessionMap(self.mapper, self.counts)  # status, snapshots, the end
        self.on_update: Callable[[Update], None] | None = None
        self.failure: str | None = None  # why the session could not go on (see fail)
        self.last_seen = time.monotonic()
        self.snapshots = Snapshots(
            store,
            session_id,
            self.counts,
            self.config.snapshot_interval_s,
            self.log,
            self._write_snapshot,
            self.meta,
        )
        self._loops_conn = loops_conn
        self._started = False
        # From the first hello on:
        self.tracker: Tracker | RoomTracker | None = None
        self.loops: LoopClosing | None = None  # online loop closure, when configured
        self.flight: Flight | None = None  # the drone
        self.flight_log: FlightLog | None = None  # its flights, recorded and saved
        self.room: RoomWriter | None = None
        self.rebuilds: MapRebuilds | None = None
        self.fusion: SessionFusion | None = None
        self.tracking: SessionTracking | None = None
        if room_dir is not None and not inherit_best(
            room_dir, best_list_paths(store, session_id), self.log
        ):
            self.counts.failed("snapshots_failed")

    # ------------------------------------------------------------------ the hello
    def configure(
        self,
        intrinsics: Intrinsics,
        client_name: str = "",
        gravity: np.ndarray | None = None,
        queued: int = 1,
    ) -> None:
        """Set the camera from the client's hello. A reconnecting client must present the same
        camera, as the map and trajectory were built with it. gravity: its direction in the
        first camera's frame (sets the drone's up; +y when None); a reconnect keeps the first.
        queued: how many of this connection's frames wait while tracking is busy
        (``protocol.queued_frames``)."""
        if self.closed:
            raise SessionError("session_closed", "this session is closed; create a new one")
        if self.intrinsics is not None and self.intrinsics != intrinsics:
            raise SessionError(
                "intrinsics_changed",
                "this session was started with another camera; create a new session",
            )
        if self.tracker is None:
            cfg = self.config.registration
            room = None  # a fresh session starts an empty world
            if self.room_dir is not None:
                room = continued_room(self.room_dir, cfg, self.mapper, self.log)
            self.tracker, self.room = track_and_keep(
                room,
                self.room_dir,
                intrinsics,
                cfg,
                self.store.folder(self.id),
                self.counts,
                self.log,
            )
            if self.loops_wanted:
                self.loops = LoopClosing(
                    intrinsics,
                    cfg,
                    self._loop_corrected,
                    self._loop_failed,
                    name=f"loops-{self.id}",
                    conn=self._loops_conn,
                )
        if self.flight is None and self.config.simulation is not None:
            self.flight, self.flight_log = make_flight(
                self.config, self.store, self.id, intrinsics, gravity, self._publish
            )
        if self.tracking is None:
            self._make_parts(intrinsics)
        if self.intrinsics is None and gravity is not None:  # a reconnect keeps the first
            g = np.asarray(gravity, dtype=np.float64)
            self.gravity = [float(v) for v in g / np.linalg.norm(g)]
        self.intrinsics = intrinsics
        self.client_name = client_name
        self.last_seen = time.monotonic()
        assert self.tracking is not None
        self.tracking.renumber(queued)  # a new connection numbers its frames afresh

    def _make_parts(self, K: Intrinsics) -> None:
        """The tracking and mapping threads' parts, wired (not started)."""
        assert self.tracker is not None and self.room is not None
        if self.loops is not None:
            self.rebuilds = MapRebuilds(
                self.mapper, self.loops, self.room, K, self.config.mapping, self.counts, self.log
            )
        self.fusion = SessionFusion(
            self.mapper,
            K,
            self.config.mapping,
            self.config.registration,
            self.counts,
            self._publish,
            self.log,
            f"map-{self.id}",
            flight=self.flight,
            room=self.room if self.config.save_room else None,
            loops=self.loops,
            rebuilds=self.rebuilds,
            snapshot_if_due=self.snapshots.take_if_due,
            fail=self.fail,
            failed=lambda: self.failure is not None,
        )
        self.tracking = SessionTracking(
            live_step(self.tracker, K, self.config),
            self.fusion,
            self.counts,
            self._publish,
            self.log,
            f"track-{self.id}",
            self.flight,
            self.frame_failed,
            self.failure_counts,
        )
        if self._started:
            self._start_parts()

    @property
    def loops_wanted(self) -> bool:
        """Online loop closure runs here (``SessionConfig.closes_loops``)."""
        return self.config.closes_loops(in_room=self.room_dir is not None)

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
        if not self._started:
            self._started = True
            self._start_parts()

    def _start_parts(self) -> None:
        if self.tracking is None or self.fusion is None:  # no hello yet: started with it
            return
        self.tracking.start()
        self.fusion.start()
        if self.loops is not None:
            self.loops.start()

    def accept(self, seq: int) -> None:
        """Frame ``seq`` arrived, before its images are decoded: counted as received, or
        refused with a SessionError (no_hello, session_failed, bad_sequence)."""
        self._open_tracking().accept(seq)

    def submit(self, frame: FrameData) -> None:
        """Queue a frame (``accept``-ed); a frame still waiting is dropped in its favour."""
        self._open_tracking().submit(frame)
        self.last_seen = time.monotonic()

    def _open_tracking(self) -> SessionTracking:
        """The tracking part, while the session takes frames; else raises SessionError."""
        if self.tracking is None:
            raise SessionError("no_hello", "send a hello before frames")
        if self.failure is not None:
            raise SessionError("session_failed", f"{self.failure}; the session has ended")
        return self.tracking

    def drain(self, timeout_s: float = 5.0) -> bool:
        """Wait until every submitted frame has been processed (or dropped); False on timeout.
        A client saying bye still gets the answers to the frames it sent."""
        return self.tracking is None or self.tracking.drain(timeout_s)

    def frame_failed(self, seq: int | None, exc: Exception, stage: str = "") -> None:
        """The server failed on frame ``seq`` (a bug, raised as ``exc``): logged with its
        traceback (call from the except block), counted, and answered internal_error."""
        self.log.exception("frame %s failed%s", seq, f" {stage}" if stage else "")
        self.counts.failed("frames_failed")
        self._publish(
            FrameRefused(
                seq,
                "internal_error",
                f"the server failed on this frame ({type(exc).__name__}: {exc})",
            )
        )

    # ------------------------------------------------------------------ loop closure
    def _loop_corrected(self, correction: Correction) -> None:
        """A verified loop corrected the world (loop thread): the tracker takes it between two
        frames, the mapping thread rebuilds the map (the newest correction wins)."""
        if self.rebuilds is not None:
            self.rebuilds.want(correction)
        if self.tracking is not None:
            self.tracking.correct(correction)

    def _loop_failed(self, exc: BaseException) -> None:
        """The loop thread failed on a keyframe (logged from its except block): counted; the
        keyframe is left out of the graph and the session goes on."""
        self.log.error("loop closure failed on a keyframe", exc_info=exc)
        self.counts.failed("loops_failed")

    def loop_figures(self) -> dict:
        """The status's ``loops``: the loop thread's counts and the map rebuilds."""
        return loop_figures(self.loops, self.rebuilds)

    # ------------------------------------------------------------------ results
    def save_room(self) -> bool:
        """Make this session's folder a room (``room/``: its keyframes, those of the room it
        continued in, and its final map) for a later session to continue in; False when it has
        no keyframe or no map. Call after the final snapshot."""
        if not self.config.save_room or self.intrinsics is None or self.room is None:
            return False
        worlds = None if self.loops is None else self.loops.worlds
        return self.room.save(
            self.id, self.intrinsics, worlds, best_list_paths(self.store, self.id)
        )

    def share_room(self, folder: Path) -> bool:
        """This live session's room as it stands, written into ``folder`` for a phone that
        joins it: a snapshot is taken now, and its map and the keyframes so far make the room
        (``RoomWriter.save``). False when there is no keyframe or no map yet. Raises
        SnapshotError when the disk refuses."""
        if not self.config.save_room or self.intrinsics is None or self.room is None:
            return False
        self.snapshot()
        worlds = None if self.loops is None else self.loops.worlds
        return self.room.save(
            self.id, self.intrinsics, worlds, best_list_paths(self.store, self.id), into=folder
        )

    def fail(self, reason: str) -> None:
        """The session cannot go on (its map is gone): frames are refused from now on, and the
        client is told (SessionFailed); the web side then stops and saves the session."""
        with self.counts.lock:
            if self.failure is not None:
                return
            self.failure = reason
        self.log.error("%s; the session ends and is saved", reason)
        self._publish(SessionFailed(reason, saved=True))

    def trajectory(self) -> Trajectory:
        if self.tracking is None:
            return Trajectory(np.zeros(0), np.zeros((0, 4, 4)))
        return self.tracking.trajectory()

    def failure_counts(self) -> dict[str, int]:
        """The session's Failures so far, by name (the drone counts its own flight errors)."""
        with self.counts.lock:
            counts = self.counts.failures.as_dict()
        if self.flight is not None:
            counts["flight_errors"] = self.flight.errors
        if self.flight_log is not None:  # a flight recording the disk refused
            counts["snapshots_failed"] += self.flight_log.saves_failed
        return counts

    def status(self) -> dict:
        # Read before the map's figures, which then hold every fusion it no longer counts.
        with self.counts.lock:
            fusion_waiting = self.counts.fusion_waiting
        map_stats = self.map.figures()
        failures = self.failure_counts()
        loops = self.loop_figures()
        poses = 0 if self.tracking is None else self.tracking.pose_count()
        c = self.counts
        with c.lock:
            return {
                "id": self.id,
                "created_at": self.created_at,
                "closed": self.closed,
                "client_name": self.client_name,
                **c.frame_figures(),
                "frames_failed": failures["frames_failed"],
                "trajectory_poses": poses,
                "map": map_stats,
                "fusion_waiting": fusion_waiting,
                "fusion_failed": failures["fusions_failed"],  # the name before failures existed
                "failures": failures,
                "failure": self.failure,
                "intrinsics": None if self.intrinsics is None else self.intrinsics.__dict__,
                "gravity": self.gravity,
                "drone": None if self.flight is None else self.flight.summary(),
                "snapshot_error": self.snapshots.error,  # why the latest snapshot failed
                "loops": loops,
            }

    def snapshot(self) -> None:
        """Write map, trajectory and meta as one snapshot (``Snapshots.take``). When the map's
        process is gone, its files stay as the previous snapshot left them. Raises
        SnapshotError when the disk refuses."""
        self.snapshots.take()

    def _write_snapshot(self, staging: Path, periodic: bool) -> list[str]:
        write_tum(staging / "trajectory.tum", self.trajectory())
        names = ["trajectory.tum"]
        if not (periodic and self.map_shared):  # a room's map: its owner's snapshots hold it
            names += self.map.save(str(staging), periodic)
        if self.flight_log is not None:  # the flight in progress, as far as it got
            self.flight_log.save_open()
        return names

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
        """Stop the threads after the frame in hand, then (optionally) write a final snapshot.
        Never waits for a mapping thread that has ended."""
        tracking, fusion = self.tracking, self.fusion
        if tracking is not None:
            tracking.stop()
        if self.flight is not None:
            self.flight.stop()
        if tracking is not None and fusion is not None and tracking.started:
            tracking.join(timeout_s=30)
            fusion.end()  # after every queued fusion
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
                self.counts.failed("room_keyframes_failed")
        self.map.close()
