"""A live session's room (server/rooms/): the saved room it continues in, if any (read at its first
hello); its keyframes written into the session's ``room/`` folder as the mapping thread fuses
them; and, when the session ends, the room itself (its keyframes, those of the room it continued
in, and its final map) for a later session."""

from __future__ import annotations

import logging
import os
import threading
from pathlib import Path

import numpy as np

from server.geometry import Intrinsics
from server.registration import Tracker
from server.registration.config import RegistrationConfig
from server.rooms.continuation import RoomTracker
from server.rooms.room import (
    MAP_FILE,
    Room,
    RoomError,
    RoomKeyframe,
    link_keyframes,
    load_room,
    room_keyframe,
    write_keyframe,
    write_room_meta,
)
from server.sessions.errors import SessionError
from server.sessions.processes.mapper import Mapper, MapperClient
from server.sessions.runtime.counts import SessionCounts
from server.sessions.runtime.loop_closing import Worlds

ROOM_FOLDER = "room"  # in a session's folder: the room it leaves (server/rooms/room.py)


def continued_room(
    room_dir: Path,
    cfg: RegistrationConfig,
    mapper: Mapper | MapperClient,
    log: logging.LoggerAdapter,
) -> Room:
    """The saved room in ``room_dir`` that a session continues in, its map loaded into the
    session's ``mapper`` (the drone's map is fed from it with the first fused frame). Raises
    SessionError (room_unusable) when the room cannot be read."""
    try:
        room = load_room(room_dir, cfg)
    except RoomError as exc:
        raise SessionError("room_unusable", str(exc)) from exc
    mapper.load(str(room_dir / MAP_FILE))
    log.info("continues in the room %s (%d keyframes)", room_dir, len(room.keyframes))
    return room


def track_and_keep(
    room: Room | None,
    room_dir: Path | None,
    K: Intrinsics,
    cfg: RegistrationConfig,
    session_folder: Path,
    counts: SessionCounts,
    log: logging.LoggerAdapter,
) -> tuple[Tracker | RoomTracker, RoomWriter]:
    """A session's tracker and the room it leaves: a fresh world without ``room``, else
    placed in it. Another phone than the room's may continue in it (a friend's, joining a
    shared room): once placed it tracks from keyframes of its own, and the room it leaves
    holds those only (one camera per room file), in the room's frame, beside the whole map."""
    if room is None:
        return Tracker(K, cfg), RoomWriter(session_folder, cfg, counts, log)
    tracker = RoomTracker(room, K, cfg, other_camera=True)
    if not tracker.same_camera:
        return tracker, RoomWriter(session_folder, cfg, counts, log)
    return tracker, RoomWriter(session_folder, cfg, counts, log, room, room_dir)


class RoomWriter:
    """The keyframes of one session's room, written into ``session_folder/room/``.

    base: the saved room (in ``base_dir``) the session continues in; its keyframes come first.
    Thread-safe: the mapping thread writes keyframes, the loop thread's corrections move their
    poses (``carry_into``), ``save`` runs when the session stops."""

    def __init__(
        self,
        session_folder: Path,
        cfg: RegistrationConfig,
        counts: SessionCounts,
        log: logging.LoggerAdapter,
        base: Room | None = None,
        base_dir: Path | None = None,
    ) -> None:
        self.session_folder = session_folder
        self.folder = session_folder / ROOM_FOLDER
        self.cfg = cfg
        self.counts = counts
        self.log = log
        self.base_dir = base_dir
        keyframes = [] if base is None else base.keyframes
        self._base_ids = [k.id for k in keyframes]
        self._base_sessions = [] if base is None else list(base.sessions)
        self._lock = threading.Lock()
        # (id, frame seq, T_world_keyframe) of every keyframe so far, and the corrected world
        # (loop closure) each pose is in (none: 0).
        self._keyframes: list[tuple[int, int, np.ndarray]] = [
            (k.id, k.frame_index, k.T_world_keyframe) for k in keyframes
        ]
        self._worlds: dict[int, int] = {}

    def keep(
        self,
        kf_id: int,
        seq: int,
        T_world_keyframe: np.ndarray,
        colour: np.ndarray,
        depth: np.ndarray,
        K: Intrinsics,
        world: int,
    ) -> RoomKeyframe | None:
        """Write a keyframe into the room folder (its features and images cost 20-40 ms, which
        the poses do not wait for); None when that failed (counted, logged: the session goes on
        without that keyframe in its room)."""
        try:
            kf = room_keyframe(kf_id, seq, T_world_keyframe, colour, depth, K, self.cfg)
            write_keyframe(self.folder, kf)
        except Exception:
            self.log.exception("keeping keyframe %d for the room failed", kf_id)
            self.counts.failed("room_keyframes_failed")
            return None
        with self._lock:
            self._keyframes.append((kf.id, kf.frame_index, kf.T_world_keyframe))
            self._worlds[kf.id] = world
        return kf

    def carry_into(self, worlds: Worlds, world: int) -> list[tuple[int, np.ndarray]]:
        """Move every keyframe's pose into the corrected world ``world``; returns (id,
        T_world_keyframe) of each, in the order written."""
        with self._lock:
            self._keyframes = [
                (i, seq, worlds.carry(i, T, self._worlds.get(i, 0), world))
                for i, seq, T in self._keyframes
            ]
            self._worlds = {i: world for i, _, _ in self._keyframes}
            return [(i, T) for i, _, T in self._keyframes]

    def save(
        self,
        session_id: str,
        K: Intrinsics,
        worlds: Worlds | None,
        carried: list[Path],
        into: Path | None = None,
    ) -> bool:
        """Make the session's folder a room (``room/``: the keyframes, each at its pose in the
        latest corrected world when ``worlds``, and the session's latest snapshot of its map);
        False when there is no keyframe or no map. The best lists (``carried``: the course's
        and the room's races', where the session has them) go with it. ``into``: another
        folder to write the room into (a live session's room, shared with a phone joining
        it), the keyframe files linked from this one."""
        with self._lock:
            keyframes = list(self._keyframes)
            kf_worlds = dict(self._worlds)
        if worlds is not None:
            keyframes = [(i, f, worlds.carry(i, T, kf_worlds.get(i, 0))) for i, f, T in keyframes]
        session_map = self.session_folder / MAP_FILE
        if not keyframes or not session_map.is_file():
            return False
        room = self.folder if into is None else into
        room.mkdir(parents=True, exist_ok=True)
        if self.base_dir is not None:
            link_keyframes(self.base_dir, room, self._base_ids)
        if room != self.folder:
            base = set(self._base_ids)
            link_keyframes(self.folder, room, [i for i, _, _ in keyframes if i not in base])
        (room / MAP_FILE).unlink(missing_ok=True)
        os.link(session_map, room / MAP_FILE)
        for best in carried:
            (room / best.name).unlink(missing_ok=True)
            if best.is_file():
                os.link(best, room / best.name)
        sessions = [
            *self._base_sessions,
            {"session": session_id, "keyframes_after": len(keyframes)},
        ]
        write_room_meta(room, K, keyframes, sessions)
        return True
