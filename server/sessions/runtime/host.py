"""A session's host: the side of a live session that runs in its worker (a process of its own,
or a Ray actor), apart from the web process.

The web process forwards what the client sent: the hello as a dict, frames as the bytes that
arrived (unpacked, validated, put in order and decoded here, so that a frame costs the event loop
no more than a look at its type), pilot commands. The host answers calls with plain values and
hands updates (poses, map points, drone states and events, refused frames) to ``publish``.
Errors cross as ``RemoteError`` values (server/sessions/processes/ipc.py).
"""

from __future__ import annotations

import os
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from server import protocol as proto
from server.errors import ConfigError
from server.evaluation.trajectory import write_tum
from server.geometry import Intrinsics
from server.rooms.continuation import RoomTracker
from server.sessions.config import SessionConfig
from server.sessions.errors import CommandRefused, SessionError
from server.sessions.processes.mapper import MapperClient
from server.sessions.processes.room_map import RoomAddress
from server.sessions.runtime.faults import inject
from server.sessions.runtime.flight import Flight
from server.sessions.runtime.session import Session
from server.sessions.store import SessionStore
from server.sessions.updates import FrameData, FrameRefused
from server.simulation.course import Gate

DOWNLOADS = ("map.ply", "mesh.ply", "trajectory.tum")


def limit_threads(threads: int) -> None:
    """Size this process's native thread pools: sessions in worker processes beside each other
    must not each assume every core is theirs. OpenCV and BLAS (the tracker's) get ``threads``;
    Open3D (the TSDF fusion's) gets one: fusion then runs alone on the mapper's thread, at its
    lower priority, and never crowds out tracking."""
    import cv2
    import open3d as o3d
    from threadpoolctl import threadpool_limits

    cv2.setNumThreads(threads)
    threadpool_limits(threads)
    o3d.utility.set_max_threads(1)


@dataclass
class HostArgs:
    """What a worker needs to host a session (pickled to the worker)."""

    session_id: str
    token_hash: str
    data_dir: str
    config: SessionConfig
    created_at: float
    threads: int  # native threads for this session's libraries
    # Tests only: stage -> the calls that fail (server/sessions/runtime/faults.py); None in service.
    faults: dict[str, list[int]] | None = None
    room_dir: str | None = None  # a saved room the session continues in (server/rooms/)
    # A live room the session joined: its map, which this session fuses into instead of a map
    # of its own (server/sessions/processes/room_map.py); None: a map of its own.
    room_map: RoomAddress | None = None


class SessionHost:
    """A live session in its worker: frames in as bytes, updates out through ``publish``."""

    def __init__(
        self,
        args: HostArgs,
        publish: Callable[[object], None],
        mapper: MapperClient | None = None,
        loops_conn=None,
    ) -> None:
        """mapper: the session's mapping process; None maps in a thread of this process.
        loops_conn: a pipe to the session's loop process; None closes loops (where configured)
        in a thread of this process."""
        limit_threads(args.threads)
        self.args = args
        self.publish = publish
        self.session = Session(
            args.session_id,
            args.token_hash,
            SessionStore(Path(args.data_dir)),
            args.config,
            created_at=args.created_at,
            mapper=mapper,
            room_dir=None if args.room_dir is None else Path(args.room_dir),
            loops_conn=loops_conn,
            map_shared=args.room_map is not None,
        )
        self._hello: dict | None = None

    def describe(self) -> dict:
        """Where this session runs, for its status."""
        return {"pid": os.getpid()}

    # ------------------------------------------------------------------ the client's messages
    def configure(self, hello: dict) -> None:
        """The client's (validated) hello: camera, name, gravity. Raises ProtocolError
        (bad_intrinsics) or SessionError (closed, another camera)."""
        fx, fy, cx, cy = hello["intrinsics"]
        width, height = hello["colour_size"]
        try:
            intrinsics = Intrinsics(fx, fy, cx, cy, int(width), int(height))
        except ConfigError as exc:
            raise proto.ProtocolError("bad_intrinsics", str(exc)) from exc
        self.session.configure(
            intrinsics,
            hello.get("client_name", ""),
            hello.get("gravity"),
            queued=proto.queued_frames(hello),
        )
        if self.args.faults and self._hello is None:
            inject(self.session, self.args.faults)
        self.session.start(self.publish)
        self._hello = hello

    def frame(self, data: bytes, received_at: float) -> None:
        """A frame message as it arrived, forwarded unread by the web process (which only peeked
        at its type and seq): the one place a frame is unpacked and validated, put in order
        (bad_sequence) and counted, before its images are decoded and it goes to the tracker.
        A frame that cannot be used is answered with a FrameRefused update, its seq in it when
        it could be read, worded as the web process words the errors it finds itself.
        ``received_at``: its arrival (``FrameData.received_at``)."""
        seq = None
        try:
            # The web process checked the size against the server's limit, which may be above
            # the protocol's default.
            message = proto.decode(data, direction=proto.CLIENT_TO_SERVER, max_bytes=len(data))
            if message["type"] != "frame":  # the web process sends frames only
                raise proto.ProtocolError("unexpected_message", "not a frame")
            seq = message["seq"]  # required in a frame, so validated with it
            if self._hello is None:
                raise SessionError("no_hello", "send a hello before frames")
            self.session.accept(seq)
            t0 = time.perf_counter()
            colour, depth = proto.decode_frame_images(message, self._hello)
            frame = FrameData(
                seq,
                message["timestamp"],
                colour,
                depth,
                received_at=received_at,
                decode_ms=(time.perf_counter() - t0) * 1e3,
                T_device_camera=None
                if message.get("T_device_camera") is None
                else np.asarray(message["T_device_camera"], dtype=np.float64).reshape(4, 4),
                device_world=message.get("device_world") or 0,
            )
            self.session.submit(frame)
        except proto.ProtocolError as exc:
            refused = exc.seq if seq is None else seq
            self.publish(FrameRefused(refused, exc.code, exc.message, counted=exc.counted))
        except SessionError as exc:
            self.publish(FrameRefused(seq, exc.code, str(exc)))
        except Exception as exc:  # a bug on one frame: the client hears internal_error
            self.session.frame_failed(seq, exc, "to decode")

    def command(self, name: str, command_id: int, fields: dict) -> None:
        """A pilot command; raises CommandRefused."""
        self.session.command(name, command_id, **fields)

    def plan_race(self, difficulty: str, seed: int | None) -> dict:
        """A course for a shared room's race, laid from where this drone is and not started
        (``CourseControl.plan``): {gates: (N, 7) world frame rows (centre, unit normal, ring
        radius; metres), difficulty, seed}. Raises CommandRefused (no drone yet, no room)."""
        flight = self._flight()
        course = flight.course.plan(difficulty, seed)
        rows = course.rows()
        centres, normals = flight.to_world(rows[:, :3]), flight.direction_to_world(rows[:, 3:6])
        gates = np.column_stack([centres, normals, rows[:, 6]])
        return {"gates": gates, "difficulty": course.spec.name, "seed": course.seed}

    def race(self, gates: np.ndarray, difficulty: str, seed: int, autopilot: bool) -> None:
        """Start the race's course (``plan_race``'s gates, world frame) from where this drone
        is: a course_start through those gates. Raises CommandRefused."""
        flight = self._flight()
        rows = np.asarray(gates, dtype=np.float64).reshape(-1, 7)
        centres, normals = flight.view.motion_in_flight(rows[:, :3], rows[:, 3:6])
        through = tuple(
            Gate(c, n, float(r)) for c, n, r in zip(centres, normals, rows[:, 6], strict=True)
        )
        flight.course.command(
            "course_start",
            None,
            difficulty=difficulty,
            seed=seed,
            autopilot=autopilot,
            through=through,
            restart_after_crash=True,  # a pilot who crashes restarts from the last gate
        )

    def _flight(self) -> Flight:
        flight = self.session.flight
        if flight is None:
            raise CommandRefused("bad_command", "no drone in this session yet (no hello)")
        return flight

    def room_drones(self, centres: np.ndarray, velocities: np.ndarray) -> None:
        """The other drones of the session's shared room, (K, 3) world centres and velocities
        (server/sessions/web/shared_rooms.py): this drone touches them."""
        flight = self.session.flight
        if flight is not None:
            flight.others_moved(centres, velocities)

    def drain(self, timeout_s: float) -> bool:
        return self.session.drain(timeout_s)

    # ------------------------------------------------------------------ REST
    def status(self) -> dict:
        tracker = self.session.tracker
        lost = tracker is not None and tracker.lost
        status = self.session.status() | {"tracking_lost": bool(lost), "threads": self.args.threads}
        if isinstance(tracker, RoomTracker):  # in a room: placed once a frame was recognised
            status["placed"] = tracker.relocalised
        return status

    def meta(self) -> dict:
        return self.session.meta()

    def download(self, name: str) -> bytes:
        """One of DOWNLOADS, as the bytes of its file. Raises MapError when there is no map."""
        if name not in DOWNLOADS:
            raise ValueError(f"unknown download {name!r}")
        if name != "trajectory.tum":
            return self.session.mapper.download(name)
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / name
            write_tum(path, self.session.trajectory())
            return path.read_bytes()

    def snapshot(self) -> None:
        self.session.snapshot()

    def share_room(self, folder: str) -> bool:
        """The room as it stands, into ``folder``, for a phone joining it (``Session.
        share_room``); False when nothing is mapped yet."""
        return self.session.share_room(Path(folder))

    def save_meta(self) -> None:
        """Write the session's meta now (a new session is on disk from its first moment)."""
        self.session.store.write_meta(self.session.id, self.session.meta())

    def set_threads(self, threads: int) -> None:
        """Resize the native thread pools (the server's share of cores for this session)."""
        self.args.threads = threads
        limit_threads(threads)

    def stop(self, save: bool) -> dict:
        """Stop after the frame in hand and (optionally) write the final snapshot; returns the
        session's meta as saved. Raises SnapshotError when the save failed (the session is
        stopped either way)."""
        self.session.stop(save=save)
        return self.session.meta()
