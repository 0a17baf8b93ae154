"""Rooms that several phones share: the owner of a live session invites (a join token), and a
phone that shows the token opens a session of its own, placed in the owner's room.

The joined session has its own tracker and drone. It continues in the owner's room: its first
frames are placed by place recognition in the room's keyframes as they stood when the phone
joined (``Session.share_room``), then it tracks in the owner's world frame and fuses into the
owner's map, the room's one map (server/sessions/processes/room_map.py; under Ray on the
owner's node: ray_workers.py). Join tokens are kept as their SHA-256 only, like session tokens,
and open nothing once the owner's session has ended.
"""

from __future__ import annotations

import hmac
import logging
import secrets
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from server.geometry import quaternion_from_pose
from server.registration.results import TrackingState
from server.rooms.room import META_FILE as ROOM_META_FILE
from server.sessions.errors import SessionError
from server.sessions.race_results import RACE_BEST_FILE, keep_race, room_best_with, write_best
from server.sessions.runtime.room_writer import ROOM_FOLDER
from server.sessions.store import hash_token
from server.sessions.updates import RoomUpdate
from server.sessions.web.live import LiveSession
from server.sessions.web.room_race import Race, race_record

log = logging.getLogger(__name__)

ROOM_HZ = 5.0  # room messages per second to each socket of a room with two or more phones
ROOM_ROUTE_POINTS = 32  # of each drone's route in a room message (protocol.json's limit)


@dataclass
class _Room:
    invites: list[str] = field(default_factory=list)  # SHA-256 of each join token
    joined: list[str] = field(default_factory=list)  # ids of the sessions that joined
    # Sessions whose drones were told of other drones (to be told of none when they go).
    told: set[str] = field(default_factory=set)
    # The owner's mapping process, the room's map: it outlives the owner's session while
    # joined phones map into it, and is reaped here once it has ended (``_reap``).
    map_process: Any = None
    race: Race | None = None  # the latest race (server/sessions/web/room_race.py)
    races: int = 0


class SharedRooms:
    """The invitations and the joined phones of every live session's room (web process).
    max_phones: phones in one room, its owner's included."""

    def __init__(
        self,
        max_phones: int,
        live_session: Callable[[str], LiveSession | None],
        folder: Callable[[str], Path] | None = None,
    ) -> None:
        """live_session: the live session with an id, or None; folder: a session's folder,
        where finished races are kept (None: they are not)."""
        self.max_phones = max_phones
        self.live_session = live_session
        self.folder = folder
        self._rooms: dict[str, _Room] = {}
        self._owner_of: dict[str, str] = {}  # joined session id -> the room owner's
        self._lock = threading.Lock()
        self._closed = threading.Event()
        self._ticker: threading.Thread | None = None

    def invite(self, owner: LiveSession | dict) -> str:
        """A new join token for the room of ``owner`` (a session its token opened; shown
        once). SessionError ``room_unavailable`` for a closed session, or one that itself
        joined a room: only the room's owner invites."""
        if not isinstance(owner, LiveSession) or owner.closed:
            raise SessionError("room_unavailable", "only a live session invites into its room")
        owner_id = owner.id
        with self._lock:
            if owner_id in self._owner_of:
                raise SessionError(
                    "room_unavailable",
                    "this phone joined another session's room: only that room's owner invites",
                )
            token = secrets.token_urlsafe(32)
            self._rooms.setdefault(owner_id, _Room()).invites.append(hash_token(token))
        return token

    def room_to_join(self, owner_id: str, token: str | None) -> LiveSession:
        """The live session whose room ``token`` (a join token) lets one more phone join.
        SessionError ``unauthorized`` without a token, ``not_found`` for a token that is not
        one of this room's (or a room that is gone: the same answer), ``room_full`` at
        ``max_phones``."""

        def live(sid: str) -> bool:
            return self.live_session(sid) is not None

        if token is None:
            raise SessionError("unauthorized", "joining a room needs its join token")
        digest = hash_token(token)
        with self._lock:
            room = self._rooms.get(owner_id)
            invited = room is not None and any(hmac.compare_digest(digest, h) for h in room.invites)
            if not invited or not live(owner_id):
                raise SessionError("not_found", "no room to join with this id for this token")
            assert room is not None
            phones = 1 + sum(live(sid) for sid in room.joined)
            if phones >= self.max_phones:
                raise SessionError(
                    "room_full", f"the room holds its maximum of {self.max_phones} phones"
                )
        owner = self.live_session(owner_id)
        if owner is None:
            raise SessionError("not_found", "no room to join with this id for this token")
        return owner

    @staticmethod
    def share(owner: LiveSession, folder: Path) -> Path:
        """The owner's room as it stands, written into ``folder`` by its worker
        (``Session.share_room``). SessionError ``room_unavailable`` while it has mapped
        nothing."""
        if not owner.worker.call("share_room", str(folder), timeout_s=60):
            raise SessionError(
                "room_unavailable",
                "the room has mapped nothing yet: let its owner map a little more, then join",
            )
        return folder

    def joined(self, owner_id: str, session_id: str) -> None:
        """``session_id`` was opened in ``owner_id``'s room; from now on every phone of the
        room is told about the others (``tell``, ROOM_HZ times a second)."""
        owner = self.live_session(owner_id)
        with self._lock:
            room = self._rooms.setdefault(owner_id, _Room())
            room.joined.append(session_id)
            self._owner_of[session_id] = owner_id
            worker = None if owner is None else owner.worker
            if getattr(worker, "room_map", None) is not None:  # its map serves the room
                worker.room_shared = True  # type: ignore[union-attr]
                room.map_process = worker.mapper_process  # type: ignore[union-attr]
            self._start_ticker()

    def _start_ticker(self) -> None:
        """The rooms thread, from the first join or race on (the caller holds the lock)."""
        if self._ticker is None:
            self._ticker = threading.Thread(target=self._tick, name="rooms", daemon=True)
            self._ticker.start()

    def close(self) -> None:
        """The server stops: no more room messages."""
        self._closed.set()

    def _tick(self) -> None:
        while not self._closed.wait(1.0 / ROOM_HZ):
            with self._lock:
                owners = list(self._rooms)
            for owner_id in owners:
                try:
                    self._start_race_if_due(owner_id)
                    self.tell(owner_id)
                    self._reap(owner_id)
                    self._forget_if_over(owner_id)
                except Exception:  # one room's bug must not silence every other room
                    log.exception("shared room %s: telling its phones failed", owner_id)

    def _forget_if_over(self, owner_id: str) -> None:
        """A room whose sessions have all ended, its map process reaped, is forgotten (a
        server running for months must not keep every room it ever had)."""
        with self._lock:
            room = self._rooms.get(owner_id)
            ids = [] if room is None else [owner_id, *room.joined]
        if room is None or room.map_process is not None:
            return
        if any(self.live_session(sid) is not None for sid in ids):
            return
        with self._lock:
            self._rooms.pop(owner_id, None)
            for sid in ids:
                self._owner_of.pop(sid, None)

    # ------------------------------------------------------------------ races
    def start_race(
        self,
        owner: LiveSession | dict,
        difficulty: str,
        seed: int | None,
        countdown_s: float,
        autopilot: bool,
    ) -> dict:
        """The room's owner starts a race: its drone's session lays a course (not started),
        and after ``countdown_s`` every live phone of the room flies its gates. Returns {race,
        gates, difficulty, seed, starts_in_s}. SessionError room_unavailable for a closed
        session or a joined phone; race_unavailable (its session's reason) when no course can
        be laid."""
        if not isinstance(owner, LiveSession) or owner.closed or owner.id in self._owner_of:
            raise SessionError(
                "room_unavailable", "only a live room's owner starts its race (this is not one)"
            )
        try:
            plan = owner.worker.call("plan_race", difficulty, seed, timeout_s=60)
        except SessionError as exc:
            if exc.code == "session_failed":
                raise
            raise SessionError("race_unavailable", f"no course for the race: {exc}") from None
        gates = np.asarray(plan["gates"], dtype=np.float64).reshape(-1, 7)
        with self._lock:
            room = self._rooms.setdefault(owner.id, _Room())
            room.races += 1
            room.race = Race(
                room.races,
                gates,
                plan["difficulty"],
                int(plan["seed"]),
                autopilot,
                time.monotonic() + countdown_s,
            )
            self._start_ticker()
        return {
            "race": room.races,
            "gates": len(gates),
            "difficulty": plan["difficulty"],
            "seed": int(plan["seed"]),
            "starts_in_s": countdown_s,
        }

    def _start_race_if_due(self, owner_id: str) -> None:
        """At the end of the countdown, every live phone of the room gets the race's course
        (``SessionHost.race``), in a thread of its own: laying a course plans a route."""
        with self._lock:
            room = self._rooms.get(owner_id)
            race = None if room is None else room.race
            if race is None or not race.due(time.monotonic()):
                return
            race.started_at, race.started_at_unix = time.monotonic(), time.time()
            ids = [owner_id, *room.joined]  # type: ignore[union-attr]
        members = [s for sid in ids if (s := self.live_session(sid)) is not None and not s.closed]
        race.pilots = [m.id for m in members]

        def start(member: LiveSession) -> None:
            try:
                member.worker.call(
                    "race", race.gates, race.difficulty, race.seed, race.autopilot, timeout_s=60
                )
            except SessionError as exc:  # that pilot is out of this race; the others fly
                race.refused[member.id] = str(exc)
                log.warning("race %d: session %s could not start: %s", race.number, member.id, exc)

        for member in members:
            threading.Thread(target=start, args=(member,), name="race-start", daemon=True).start()

    def _keep_race(
        self, owner_id: str, race: Race, members: list[LiveSession], standings: dict
    ) -> None:
        """A race just finished: its record and the room's best list go into every pilot's
        session folder (server/sessions/race_results.py), and into the owner's saved room
        when it has one already (its session ended before the race did)."""
        if race.recorded or self.folder is None:
            return
        race.recorded = True
        record = race_record(race, owner_id, members, standings, time.time())
        best = room_best_with(self.folder(owner_id), record)
        folders = [self.folder(m.id) for m in members]
        if self.live_session(owner_id) is None and owner_id not in [m.id for m in members]:
            folders.append(self.folder(owner_id))
        for folder in folders:
            try:
                keep_race(folder, record, best)
            except OSError:
                log.exception("race %d: its record could not be kept in %s", race.number, folder)
        room = self.folder(owner_id) / ROOM_FOLDER
        if (room / ROOM_META_FILE).is_file():
            try:
                write_best(room / RACE_BEST_FILE, best)
            except OSError:
                log.exception("race %d: the room's best list could not be saved", race.number)
        log.info("race %d finished: %s", race.number, record["pilots"])

    def _reap(self, owner_id: str) -> None:
        """Once the owner's session has ended, its mapping process ends after the last
        joined phone has gone: collect it then (``is_alive`` waits for an ended child)."""
        with self._lock:
            room = self._rooms.get(owner_id)
            process = None if room is None else room.map_process
        if process is None or self.live_session(owner_id) is not None or process.is_alive():
            return
        process.join(timeout=0)
        with self._lock:
            if room is not None:
                room.map_process = None

    def tell(self, owner_id: str) -> None:
        """Give every live phone of ``owner_id``'s room (and its viewer links) the room's
        state: each phone's name, placement, drone and camera, as its latest updates left
        them, while two or more phones are live."""
        with self._lock:
            room = self._rooms.get(owner_id)
            ids = [owner_id] + ([] if room is None else list(room.joined))
            race = None if room is None else room.race
        # The owner's session may have ended: the room's map serves the joined phones on.
        members = [s for sid in ids if (s := self.live_session(sid)) is not None and not s.closed]
        if len(members) < 2 and race is None:
            self._tell_drones(room, members, None)
            return
        n = len(members)
        placed, modes = [False] * n, ["none"] * n
        drones, cameras = np.zeros((n, 7)), np.zeros((n, 7))
        velocities = np.zeros((n, 3))
        routes: list[np.ndarray | None] = [None] * n
        for i, member in enumerate(members):
            pose, drone = member.viewers.latest()
            if pose is not None and pose.state is not TrackingState.LOST:
                placed[i] = True
                cameras[i] = _centre_and_rotation(pose.T_world_camera)
            if drone is not None:
                modes[i] = drone.mode
                drones[i] = _centre_and_rotation(drone.T_world_drone)
                velocities[i] = drone.velocity
                routes[i] = _shortened(drone.route)
        names = [m.client_name for m in members]
        standings = None if race is None else race.standings(members, time.monotonic())
        if race is not None and standings is not None and standings["race"] == "finished":
            self._keep_race(owner_id, race, members, standings)
        for i, member in enumerate(members):
            member.deliver(RoomUpdate(names, i, placed, modes, drones, cameras, standings, routes))
        flying = np.array([m != "none" for m in modes])
        # While a race runs the drones are ghosts to each other, as in a racing game's time
        # trial: all fly the same line through the same gates, and none may block another.
        racing = standings is not None and standings["race"] != "finished"
        self._tell_drones(room, members, None if racing else (flying, drones[:, :3], velocities))

    def _tell_drones(
        self,
        room: _Room | None,
        members: list[LiveSession],
        drones: tuple[np.ndarray, np.ndarray, np.ndarray] | None,
    ) -> None:
        """Each member's drone is told where the others are (``SessionHost.room_drones``),
        to touch them: ``drones`` = (whether each has one, centres, velocities), world frame;
        None: there are no others any more (told once, to those told before)."""
        if room is None:
            return
        for i, member in enumerate(members):
            if drones is None and member.id not in room.told:
                continue
            others = np.zeros(0, bool) if drones is None else drones[0].copy()
            if drones is not None:
                others[i] = False
            centres = np.zeros((0, 3)) if drones is None else drones[1][others]
            velocities = np.zeros((0, 3)) if drones is None else drones[2][others]
            try:
                member.worker.post("room_drones", centres, velocities)
            except SessionError:  # its worker is gone: its own path reports that
                continue
            if drones is None:
                room.told.discard(member.id)
            else:
                room.told.add(member.id)

    def owner_of(self, session_id: str) -> str | None:
        """The id of the room's owner that ``session_id`` joined, or None."""
        with self._lock:
            return self._owner_of.get(session_id)

    def phones(self, owner_id: str) -> list[str]:
        """The sessions that joined ``owner_id``'s room, in the order they joined."""
        with self._lock:
            room = self._rooms.get(owner_id)
            return [] if room is None else list(room.joined)


def _shortened(route: np.ndarray | None) -> np.ndarray | None:
    """A route (K, 3) as the room message carries it: at most ROOM_ROUTE_POINTS, its first
    ones and its goal (the room's view of a route, not one to fly)."""
    if route is None or len(route) == 0:
        return None
    if len(route) <= ROOM_ROUTE_POINTS:
        return route
    return np.vstack([route[: ROOM_ROUTE_POINTS - 1], route[-1:]])


def _centre_and_rotation(T: np.ndarray) -> np.ndarray:
    """x, y, z (metres) and the rotation's quaternion x, y, z, w of a 4x4 transform."""
    return np.concatenate([T[:3, 3], quaternion_from_pose(T)])
