"""The session's drone: a simulator flying in the session's map, advanced in real time.

The simulator works in a gravity-aligned flight frame (z up); the session's world frame is the
first camera's frame, whose axes need not be level. This module owns the rotation between the
two, keeps the flight map fed from the TSDF (``feed_from_map`` after each fused frame: the
sub-box of occupancy that frame can have changed), turns the pilot's commands (world targets, tapped
pixels, sticks) into simulator calls, and publishes the drone's state in the world frame.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from server.geometry import Intrinsics, invert
from server.sessions.course import COURSE_COMMANDS, CourseControl
from server.sessions.errors import CommandRefused
from server.sessions.failures import RateLimitedLog
from server.sessions.updates import DroneNotice, DroneUpdate
from server.simulation.config import SimulationConfig
from server.simulation.drone import DroneCommandError, DroneSimulator
from server.simulation.flight_map import FlightMap, Region
from server.simulation.flight_recording import FlightRecorder
from server.simulation.pilot_modes import euler_from_rotation
from server.simulation.planner import PlanningError

log = logging.getLogger(__name__)

_PIXEL_WINDOW = 3  # half-size of the window a tapped pixel's depth is read from, px
_RECENT_FRAMES = 8  # frames kept for goto_pixel
_TAP_SLACK_M = 0.6  # a tapped target may move this far to the nearest reachable point, m
# Flight steps failing in a row before the drone is stopped for good (faulted): half a second
# at 20 Hz. A failure or two (a bad map update) is counted and flown through.
_MAX_FAILING_STEPS = 10


_REFUSALS = {  # PlanningError reasons, for the pilot
    "goal_blocked": "inside or too close to an obstacle, or in space the camera has not seen",
    "outside_map": "outside the mapped space",
    "unreachable": "no collision-free route reaches it",
    "start_blocked": "the drone has no room to move",
    "not_finite": "not three finite numbers",
}


def _xyz(p: np.ndarray) -> str:
    return "(" + ", ".join(f"{v:.2f}" for v in p) + ") m"


def flight_frame(gravity_world: np.ndarray | None) -> np.ndarray:
    """R_flight_world (3x3): flight z is against gravity, flight x the first camera's optical
    axis made level. gravity_world: gravity's direction in the world (= first camera) frame;
    None means +y, a camera held upright and level."""
    g = np.array([0.0, 1.0, 0.0]) if gravity_world is None else np.asarray(gravity_world, float)
    up = -g / np.linalg.norm(g)
    for forward in (np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0])):
        x = forward - forward.dot(up) * up
        if np.linalg.norm(x) > 1e-3:  # the camera looked straight up or down: use its x axis
            break
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(up, x), up])


# What a flight recording keeps of a course message (PROTOCOL.md, "Flight recordings").
_COURSE_FIELDS = ("course_id", "difficulty", "seed", "gates", "par_s", "autopilot")
_RESULT_FIELDS = ("course_id", "elapsed_s", "par_s", "score", "bumps", "crashes", "rank")


@dataclass
class _CameraFrame:
    T_world_camera: np.ndarray
    depth: np.ndarray  # (H, W) metres at the colour image's size, 0 = none


class Flight:
    """One session's drone. ``camera_moved`` and ``feed_from_map`` (or ``map_changed``) come
    from the session's workers, ``command`` from the transport; a thread of its own advances the
    simulation in real time and hands ``DroneUpdate``/``DroneNotice`` objects (and the course's
    ``course`` messages, dicts: ``course``, server/sessions/course.py) to ``publish``.

    A flight step that raises is counted (``errors``) and logged, the first with its traceback,
    then at most one line per 10 s; after _MAX_FAILING_STEPS in a row the drone is stopped for
    good (``fault`` says why): its thread ends, a last drone_state says mode ``faulted`` (at
    rest where it was), a drone_event ``faulted`` says why, and commands are refused."""

    def __init__(
        self,
        config: SimulationConfig,
        K: Intrinsics,
        gravity_world: np.ndarray | None,
        publish: Callable[[DroneUpdate | DroneNotice | dict], None],
        state_hz: float = 20.0,
        spawn_ahead_m: float = 0.8,
        log: logging.LoggerAdapter | logging.Logger = log,
    ) -> None:
        self.config = config
        self.log = log
        self.K = K
        self.R_flight_world = flight_frame(gravity_world)
        self.T_world_flight = np.eye(4)  # constant: the state at 20 Hz needs it
        self.T_world_flight[:3, :3] = self.R_flight_world.T
        self.publish = publish
        self.state_period_s = 1.0 / state_hz
        self.spawn_ahead_m = spawn_ahead_m
        self.flight_map = FlightMap(config.voxel_m, unknown_is_free=config.unknown_is_free)
        self.sim = DroneSimulator(config, self.flight_map)
        self.course = CourseControl(self)  # courses: server/sessions/course.py
        self._lock = threading.Lock()  # the simulator and flight map are used by one thread at once
        # Camera frames have their own lock: tracking never waits for planning or physics.
        self._frames_lock = threading.Lock()
        self._frames: OrderedDict[int, _CameraFrame] = OrderedDict()  # by seq, newest last
        # Map changes waiting for the flight thread: a whole grid, then the sub-boxes that came
        # after it merged into one. Their own lock: the mapping thread never waits for physics.
        self._pending_lock = threading.Lock()
        self._pending_map: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._pending_region: Region | None = None
        self._pending_frames: int | None = None
        # A map rebuilt in a corrected world (loop closure) with the drone's move into it
        # (old world to new, world frame); regions pending before it belonged to the old map.
        self._pending_world: tuple[tuple[np.ndarray, np.ndarray, np.ndarray], np.ndarray] | None
        self._pending_world = None
        self.corrections = 0  # corrected worlds the drone moved into
        # The client's world from the simulation's (4x4, metres): the loop corrections the
        # tracker has taken (map_corrected went out, poses come in the corrected world) that the
        # drone and its map have not yet (the map is rebuilt in the background, seconds later).
        # Everything the drone reports goes out through it and every target comes in through
        # it, so the drone stays where it was relative to the camera meanwhile.
        self._T_view_sim = np.eye(4)
        self._view_lock = threading.Lock()  # taken after _lock where both are held
        # Fused frames the flight map holds (the session's count; for clients that must know
        # whether the drone's map has caught up with map.frames_integrated).
        self.map_frames = 0
        self.event_counts: dict[str, int] = {}  # drone events so far, by kind
        self.errors = 0  # flight steps that raised
        self.fault: str | None = None  # why the drone was stopped for good, if it was
        self._failed_steps = RateLimitedLog(self.log)
        self._last_state: DroneUpdate | None = None
        # Records every flight (server/simulation/flight_recording.py); set by the session. A
        # course judge attaches its course and result here: recorder.set_course(course_dict),
        # recorder.finish(result_dict) (plain JSON-able dicts; finish ends the flight).
        self.recorder: FlightRecorder | None = None
        self._recorded_course: int | None = None  # course_id attached to the recording
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    @property
    def spawned(self) -> bool:
        return self.sim.spawned

    # ------------------------------------------------------------------ frames
    def _T_world_flight_shown(self) -> np.ndarray:
        """T_world_flight (4x4, metres) into the client's world: the tracker's, which may be
        ahead of the simulation's by loop corrections not yet rebuilt into the map."""
        with self._view_lock:
            return self._T_view_sim @ self.T_world_flight

    @property
    def lock(self) -> threading.Lock:
        """The lock the simulator and flight map are used under (CourseFlight)."""
        return self._lock

    def _to_flight(self, p_world: np.ndarray) -> np.ndarray:
        """A point (3,) of the client's world in the flight frame."""
        T = invert(self._T_world_flight_shown())
        return T[:3, :3] @ np.asarray(p_world, dtype=np.float64) + T[:3, 3]

    def to_world(self, p_flight: np.ndarray) -> np.ndarray:
        """Flight-frame points ((3,) or (N, 3)) in the client's world."""
        T = self._T_world_flight_shown()
        return np.asarray(p_flight, dtype=np.float64) @ T[:3, :3].T + T[:3, 3]

    def direction_to_world(self, v_flight: np.ndarray) -> np.ndarray:
        """Flight-frame directions or velocities ((3,) or (N, 3)) in the client's world."""
        return np.asarray(v_flight, dtype=np.float64) @ self._T_world_flight_shown()[:3, :3].T

    def world_corrected(self, T_correction: np.ndarray) -> None:
        """The tracker moved into a corrected world (loop closure; the client was sent
        map_corrected): T_correction (4x4, metres) maps the old world into the new one. The drone
        is reported in the new world from now on, while it still flies the old map until
        ``map_replaced`` brings the rebuilt one. The recent camera frames move with the
        world too (a tap on a frame from before the correction still lands where it showed).
        Tracking-thread side."""
        T = np.asarray(T_correction, dtype=np.float64)
        with self._frames_lock:
            for frame in self._frames.values():
                frame.T_world_camera = T @ frame.T_world_camera
        with self._view_lock:
            self._T_view_sim = T @ self._T_view_sim

    # ------------------------------------------------------------------ inputs
    def camera_moved(self, seq: int, T_world_camera: np.ndarray, depth: np.ndarray) -> None:
        """A processed frame: its pose (and depth, for tapped pixels). Tracking-thread side."""
        with self._frames_lock:
            self._frames.pop(seq, None)  # a reconnected client numbers from 0 again
            self._frames[seq] = _CameraFrame(T_world_camera, depth)
            while len(self._frames) > _RECENT_FRAMES:
                self._frames.popitem(last=False)

    def map_changed(self, origin: np.ndarray, occupied: np.ndarray, observed: np.ndarray) -> None:
        """A new whole occupancy grid in the flight frame (``TSDFMap.occupancy(voxel_m,
        R_grid_world=R_flight_world)``); it replaces whatever is pending, and the flight thread
        applies it."""
        with self._pending_lock:
            self._pending_map = (origin, occupied, observed)
            self._pending_region = None

    def map_replaced(
        self,
        origin: np.ndarray,
        occupied: np.ndarray,
        observed: np.ndarray,
        T_correction: np.ndarray,
        frames: int | None = None,
    ) -> None:
        """The session's map was rebuilt in a corrected world (loop closure): the whole new grid
        (flight frame, as ``map_changed``) and ``T_correction`` (4x4, world frame, metres: old
        world to new). The flight thread replaces the flight map and moves the drone with the
        world in one step (``DroneSimulator.move_with_world``), so it never flies a moved map
        from an unmoved place; what was pending for the old map is dropped."""
        T_move = np.asarray(T_correction, dtype=np.float64)
        with self._pending_lock:
            if self._pending_world is not None:  # two rebuilds before a step: moves compose
                T_move = T_move @ self._pending_world[1]
            self._pending_world = ((origin, occupied, observed), T_move)
            self._pending_map = None
            self._pending_region = None
            if frames is not None:
                self._pending_frames = frames

    def map_region_changed(
        self,
        origin: np.ndarray,
        occupied: np.ndarray,
        observed: np.ndarray,
        frames: int | None = None,
    ) -> None:
        """New occupancy for a sub-box of the grid, flight frame (``TSDFMap.occupancy_update``:
        origin (3,) metres on the grid's lattice, occupied and observed (X, Y, Z) bool). Cheap
        to call often: boxes pending together merge (the newer wins where they overlap) and
        the flight thread applies them in one update. ``frames``: how many fused frames the
        flight map holds once this is applied (``map_frames``)."""
        region = Region.whole(origin, occupied, observed)
        with self._pending_lock:
            pending = self._pending_region
            self._pending_region = (
                region if pending is None else pending.merged(region, self.flight_map.voxel_m)
            )
            if frames is not None:
                self._pending_frames = frames

    def map_includes(self, frames: int) -> None:
        """The frames fused since the last update changed nothing the drone's grid holds: the
        flight map holds ``frames`` fused frames once what is pending is applied."""
        with self._pending_lock:
            self._pending_frames = frames

    def feed_from_map(self, tsdf_map) -> bool:
        """Hand the drone what the frames fused into ``tsdf_map`` (a ``TSDFMap``) since the last
        call can have changed: call it after each integrate, from the thread that fuses. The
        first call hands over the whole map. Returns whether anything was handed over; never
        raises (a failure is logged: the drone must not stop the mapping)."""
        try:
            update = tsdf_map.occupancy_update(self.config.voxel_m, self.R_flight_world)
            if update is None:
                return False
            self.map_region_changed(*update)
            return True
        except Exception:
            log.exception("feeding the flight map from the TSDF failed")
            return False

    def command(
        self,
        name: str,
        command_id: int,
        *,
        target=None,
        pixel=None,
        seq=None,
        sticks=None,
        speed=None,
        flight_mode=None,
        **options,
    ) -> None:
        """Carry out a pilot command (names and fields as the protocol's ``command``; fields
        no drone command reads arrive in ``options``). Raises CommandRefused (code
        bad_command or unreachable_target)."""
        if self.fault is not None:
            raise CommandRefused(
                "bad_command",
                f"the drone's simulation failed and the drone is stopped ({self.fault}); "
                "create a new session to fly again",
            )
        if name in COURSE_COMMANDS:
            self.course.command(name, command_id, speed=speed, **options)
            return
        if not self.spawned and name not in ("sticks", "flight_mode"):
            raise CommandRefused(
                "bad_command",
                "the drone appears once the map has its first "
                "frames; wait for the drone_event 'spawned'",
            )
        asked = {"target": target, "pixel": pixel, "seq": seq, "sticks": sticks, "speed": speed}
        if name == "goto_pixel":
            target = self._pixel_target(pixel, seq)
        with self._lock:
            try:
                if name == "goto":
                    self._goto(np.asarray(target, dtype=np.float64), speed, command_id)
                elif name == "goto_pixel":
                    self._goto_near(target, speed, command_id)
                elif name == "sticks":
                    if self.spawned:  # sticks stream from the page before the drone exists
                        self.sim.command_sticks(self._sticks(sticks), command_id=command_id)
                elif name == "hold":
                    self.sim.command_hold(command_id=command_id)
                elif name == "land":
                    self.sim.command_land(command_id=command_id)
                elif name == "takeoff":
                    self.sim.command_takeoff(command_id=command_id)
                elif name == "flight_mode":
                    self.sim.set_flight_mode(flight_mode, command_id=command_id)
                else:
                    raise CommandRefused("bad_command", f"unknown drone command {name!r}")
            except DroneCommandError as exc:
                raise CommandRefused("bad_command", str(exc)) from None
            now_s = self.sim.time_s if self.spawned else 0.0
        if self.recorder is not None:
            try:
                self.recorder.command(now_s, name, command_id, asked)
            except Exception:  # the command was carried out; only its record is missing
                self.errors += 1
                self._failed_steps.failure("recording a command")

    @staticmethod
    def _sticks(sticks) -> np.ndarray:
        values = np.asarray(sticks, dtype=np.float64).reshape(-1)
        if values.size != 4 or not np.all(np.isfinite(values)):
            raise CommandRefused("bad_command", "sticks must be 4 finite numbers in -1..1")
        return np.clip(values, -1.0, 1.0)

    def _goto(self, target_world: np.ndarray, speed: float | None, command_id: int) -> None:
        if not np.all(np.isfinite(target_world)):
            raise CommandRefused("bad_command", "the target must be three finite numbers")
        try:
            self.sim.command_goto(self._to_flight(target_world), speed=speed, command_id=command_id)
        except PlanningError as exc:
            # The planner speaks in flight-frame coordinates; the client knows the world's.
            nearest = None if exc.nearest is None else self.to_world(exc.nearest)
            code = "bad_command" if exc.reason == "not_finite" else "unreachable_target"
            why = _REFUSALS.get(exc.reason.value, str(exc))
            message = f"target {_xyz(target_world)}: {why}"
            if nearest is not None:
                message += f"; nearest reachable point {_xyz(nearest)}"
            raise CommandRefused(code, message, nearest) from None

    def _goto_near(self, target_world: np.ndarray, speed: float | None, command_id: int) -> None:
        """A tap means 'over there': when the exact point is too close to something, fly to the
        nearest reachable point if it is within _TAP_SLACK_M."""
        try:
            self._goto(target_world, speed, command_id)
        except CommandRefused as exc:
            if exc.nearest is None or np.linalg.norm(exc.nearest - target_world) > _TAP_SLACK_M:
                raise
            self._goto(exc.nearest, speed, command_id)

    def _pixel_target(self, pixel, seq: int | None) -> np.ndarray:
        """The world point a tapped pixel shows, standoff_m back towards the camera."""
        with self._frames_lock:
            if seq is None and self._frames:
                seq = next(reversed(self._frames))
            frame = None if seq is None else self._frames.get(seq)
        if frame is None:
            raise CommandRefused(
                "bad_command",
                f"frame {seq} is not among the last {_RECENT_FRAMES} processed frames; tap again",
            )
        u, v = float(pixel[0]), float(pixel[1])
        h, w = frame.depth.shape
        if not (0 <= u < w and 0 <= v < h):
            raise CommandRefused(
                "bad_command", f"pixel ({u:.0f}, {v:.0f}) is outside the {w}x{h} image"
            )
        r = _PIXEL_WINDOW
        window = frame.depth[
            max(0, int(v) - r) : int(v) + r + 1, max(0, int(u) - r) : int(u) + r + 1
        ]
        valid = window[(window > 0) & np.isfinite(window)]
        if valid.size == 0:
            raise CommandRefused(
                "bad_command",
                f"no depth at pixel ({u:.0f}, {v:.0f}); tap a surface the camera measured",
            )
        z = float(np.median(valid))
        K = self.K
        ray = np.array([(u - K.cx) / K.fx, (v - K.cy) / K.fy, 1.0])
        distance = z * np.linalg.norm(ray)
        back_off = min(self.config.standoff_m, 0.8 * distance)
        p_camera = ray / np.linalg.norm(ray) * (distance - back_off)
        T = frame.T_world_camera
        return T[:3, :3] @ p_camera + T[:3, 3]

    # ------------------------------------------------------------------ the flight thread
    def start(self) -> None:
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="flight", daemon=True)
            self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)

    def _run(self) -> None:
        last = due = time.monotonic()
        failing = 0  # steps failed in a row
        while True:
            # A fixed schedule (the wait is the period less the step's own time), so states go
            # out at drone_state_hz, not a little below it (flight recordings keep that rate);
            # after a step that overran a whole period the schedule starts afresh, a period on,
            # rather than bunching the next steps.
            due += self.state_period_s
            if due < time.monotonic():
                due = time.monotonic() + self.state_period_s
            if self._stop.wait(max(0.0, due - time.monotonic())):
                return
            now = time.monotonic()
            # A starved thread slows the drone down rather than letting it jump.
            dt, last = min(now - last, 0.25), now
            try:
                notices = self._tick(dt)
                state = self.state() if self.spawned else None
            except Exception as exc:  # the drone must never take the session down
                self.errors += 1
                failing += 1
                self._failed_steps.failure("a flight step")
                if failing >= _MAX_FAILING_STEPS:
                    self._stop_faulted(f"{type(exc).__name__}: {exc}", failing)
                    return
                continue
            failing = 0
            for notice in notices:
                self.publish(notice)
            if state is not None:
                self._last_state = state
                self.publish(state)
            self._record(notices, state)

    def record_course(self, message: dict) -> None:
        """Attach a ``course`` message's course to the flight being recorded; a finished
        course's result (score, time, gates, bumps, crashes, rank) ends that flight, a stopped
        one is detached. Called with each course message sent (under the flight's lock only for
        a start or a stop, which write nothing to disk)."""
        recorder = self.recorder
        if recorder is None:
            return
        try:
            state = message["state"]
            if state == "running" and message["course_id"] != self._recorded_course:
                recorder.set_course({k: message[k] for k in _COURSE_FIELDS})
                self._recorded_course = message["course_id"]
            elif state == "finished" and message["course_id"] == self._recorded_course:
                result = {k: message[k] for k in _RESULT_FIELDS}
                result["gates_passed"] = message["gate_states"].count("passed")
                result["gates_missed"] = message["gate_states"].count("missed")
                recorder.finish(result)
                recorder.set_course(None)
                self._recorded_course = None
            elif state == "stopped" and self._recorded_course is not None:
                recorder.set_course(None)
                self._recorded_course = None
        except Exception:  # a recording that fails must not stop the course: counted, logged
            self.errors += 1
            self._failed_steps.failure("recording a course")

    def _record(self, notices: list[DroneNotice | dict], state: DroneUpdate | None) -> None:
        """Hand the step's events, course messages and state to the flight recorder, if any."""
        if self.recorder is None:
            return
        try:
            for n in notices:
                if isinstance(n, dict):
                    if n.get("type") == "course":
                        self.record_course(n)
                    continue
                self.recorder.event(n.timestamp, n.event, n.position, n.message, n.command_id)
            if state is not None:
                self.recorder.state(
                    state.timestamp, state.T_world_drone, state.velocity, state.mode
                )
        except Exception:  # a recording that fails must not stop the drone: counted, logged
            self.errors += 1
            self._failed_steps.failure("recording a flight step")

    def _stop_faulted(self, reason: str, failing: int) -> None:
        """Stop the drone for good: its simulation failed ``failing`` steps in a row."""
        self.fault = reason
        self.log.error(
            "the drone is stopped: %d flight steps in a row failed (%s)", failing, reason
        )
        final = self.state()  # the last good state, at rest, mode faulted
        if final is None:
            return  # never spawned: the client has no drone to hear about
        notice = DroneNotice(
            "faulted",
            final.timestamp,
            final.T_world_drone[:3, 3],
            f"the drone's simulation failed and the drone is stopped ({reason}); "
            "create a new session to fly again",
            None,
        )
        self.publish(notice)
        self.publish(final)
        self._record([notice], final)

    def _tick(self, dt: float) -> list[DroneNotice | dict]:
        with self._lock:
            events = []
            with self._pending_lock:
                grid, region = self._pending_map, self._pending_region
                frames, world = self._pending_frames, self._pending_world
                self._pending_map = self._pending_region = self._pending_frames = None
                self._pending_world = None
            if world is not None:
                T_move = world[1]
                T_delta = invert(self.T_world_flight) @ T_move @ self.T_world_flight
                self.sim.move_with_world(T_delta, *world[0])
                self.course.move_with_world(T_delta)
                with self._view_lock:  # what the client saw moved into the simulation itself
                    self._T_view_sim = self._T_view_sim @ invert(T_move)
                self.corrections += 1
            if grid is not None:
                self.sim.update_map(*grid)
            if region is not None:
                self.sim.update_map_region(region)
            if frames is not None:
                self.map_frames = frames
            if grid is not None or region is not None or world is not None:
                if not self.spawned and (camera := self._latest_camera()) is not None:
                    self._spawn(camera[1])
            course = []
            if self.spawned:
                events = self.sim.advance(dt)
                course = self.course.tick(events)  # gate notices and course messages
        notices = [self._notice(e) for e in events] + course
        for n in notices:
            if isinstance(n, DroneNotice):
                self.event_counts[n.event] = self.event_counts.get(n.event, 0) + 1
        return notices

    def _latest_camera(self) -> tuple[int, np.ndarray] | None:
        """(seq, T_world_camera) of the newest processed frame."""
        with self._frames_lock:
            if not self._frames:
                return None
            seq = next(reversed(self._frames))
            return seq, self._frames[seq].T_world_camera

    def _spawn(self, T: np.ndarray) -> None:
        """Hover spawn_ahead_m in front of the camera, facing away from it, in observed free
        space; next to the camera when the space ahead is not known yet."""
        forward = invert(self._T_world_flight_shown())[:3, :3] @ T[:3, 2]
        yaw = float(np.arctan2(forward[1], forward[0]))
        for near in (T[:3, 3] + self.spawn_ahead_m * T[:3, 2], T[:3, 3]):
            try:
                self.sim.spawn(self._to_flight(near), yaw_rad=yaw)
                return
            except DroneCommandError:
                continue

    def _notice(self, event) -> DroneNotice:
        return DroneNotice(
            event.kind.value,
            event.time_s,
            self.to_world(event.position),
            event.text(self.to_world),  # the pilot's frame, as the event's other fields
            event.command_id,
        )

    def state(self) -> DroneUpdate | None:
        """The drone's state now; once faulted, its last good state at rest (None when it
        never spawned)."""
        if self.fault is not None:
            if self._last_state is None:
                return None
            return replace(
                self._last_state,
                mode="faulted",
                velocity=np.zeros(3),
                target=None,
                route=None,
            )
        with self._lock:  # the simulation and the view it is shown in, from one step
            s = self.sim.status()
            T_world_flight = self._T_world_flight_shown()
        camera = self._latest_camera()
        T_world_drone = T_world_flight @ s.T_flight_drone
        T_camera_drone = None if camera is None else invert(camera[1]) @ T_world_drone
        route = None if s.route is None or len(s.route) == 0 else self.to_world(s.route)
        return DroneUpdate(
            timestamp=s.time_s,
            T_world_drone=T_world_drone,
            T_camera_drone=T_camera_drone,
            camera_seq=None if camera is None else camera[0],
            velocity=self.direction_to_world(s.velocity),
            mode=s.mode.value,
            clearance=float(s.clearance),
            target=None if s.target is None else self.to_world(s.target),
            route=route,
            command_id=s.command_id,
            flight_mode=s.flight_mode.value,
            attitude=np.degrees(euler_from_rotation(tuple(s.T_flight_drone[:3, :3].ravel()))),
            damage=s.damage,
        )

    def summary(self) -> dict:
        """For the session's status endpoint: ``errors`` counts the flight steps that failed;
        ``fault`` (when the drone was stopped for good) says why, and ``mode`` is faulted."""
        health = {
            "errors": self.errors,
            "fault": self.fault,
            "map_frames": self.map_frames,
            "corrections": self.corrections,
        }
        s = self.state() if self.spawned or self.fault is not None else None
        if s is None:
            return {"spawned": False, **health}
        return {
            "spawned": True,
            "mode": s.mode,
            "position": s.T_world_drone[:3, 3].tolist(),
            "clearance_m": s.clearance,
            "damage": s.damage,
            "events": dict(self.event_counts),
            **health,
        }
