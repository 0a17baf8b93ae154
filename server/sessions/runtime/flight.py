"""The session's drone: a simulator flying in the session's map, advanced in real time.

The simulator works in a gravity-aligned flight frame (z up); the session's world frame is the
first camera's frame, whose axes need not be level (flight_view.py maps between the two). This
module keeps the flight map fed from the TSDF (``feed_from_map`` after each fused frame: the
sub-box of occupancy that frame can have changed; pending_map.py holds it for the flight
thread), turns the pilot's commands (world targets, tapped pixels of recent frames:
camera_frames.py, sticks) into simulator calls, runs the flight thread, and publishes the
drone's state in the world frame.

One lock, ``Flight.lock``, is held around every use of the simulator, its flight map and the
course: the flight thread's step, a command, a state. ``Flight`` owns it rather than the
simulator because what must not interleave spans more than the simulator: a step applies the
pending map changes, moves drone and course into a corrected world, advances the physics and
judges the course, and a course command stops the drone and copies the map, all as one.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import replace

import numpy as np

from server.geometry import Intrinsics, invert
from server.sessions.errors import CommandRefused
from server.sessions.failures import RateLimitedLog
from server.sessions.runtime.camera_frames import CameraFrames
from server.sessions.runtime.course_control import COURSE_COMMANDS, CourseControl
from server.sessions.runtime.flight_records import FlightRecords
from server.sessions.runtime.flight_view import FlightView
from server.sessions.runtime.pending_map import PendingMap
from server.sessions.runtime.pilot_commands import carry_out
from server.sessions.updates import DroneNotice, DroneUpdate
from server.simulation.config import SimulationConfig
from server.simulation.drone import DroneSimulator
from server.simulation.drone_types import DroneCommandError, DroneEventKind
from server.simulation.flight_map import FlightMap
from server.simulation.flight_recording import FlightRecorder
from server.simulation.map_regions import Region
from server.simulation.other_drones import OtherDrones
from server.simulation.pilot_modes import euler_from_rotation

log = logging.getLogger(__name__)

# Flight steps failing in a row before the drone is stopped for good (faulted): half a second
# at 20 Hz. A failure or two (a bad map update) is counted and flown through.
_MAX_FAILING_STEPS = 10


class Flight:
    """One session's drone. ``camera_moved`` and ``feed_from_map`` (or ``map_changed``) come from
    the session's workers, ``command`` from the transport; a thread of its own advances the
    simulation in real time and hands ``DroneUpdate``/``DroneNotice`` objects (and the course's
    ``course`` messages, dicts: ``course``, server/sessions/runtime/course_control.py) to
    ``publish``.

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
        self.view = FlightView(gravity_world)  # flight frame <-> the client's world
        self.R_flight_world = self.view.R_flight_world  # constant, as T_world_flight
        self.T_world_flight = self.view.T_world_flight
        self.publish = publish
        self.state_period_s = 1.0 / state_hz
        self.spawn_ahead_m = spawn_ahead_m
        self.flight_map = FlightMap(config.voxel_m, unknown_is_free=config.unknown_is_free)
        self.sim = DroneSimulator(config, self.flight_map)
        self.course = CourseControl(self)  # courses: server/sessions/runtime/course_control.py
        # One lock over simulator, flight map and course (module docstring); the sim has none.
        self._lock = threading.Lock()
        # Camera frames and pending map changes have their own locks, taken after this one where
        # both are held: tracking and mapping never wait for planning or physics.
        self.frames = CameraFrames(K, config.standoff_m)
        self.pending = PendingMap(config.voxel_m)
        self.corrections = 0  # corrected worlds the drone moved into
        self.others = OtherDrones(config.radius_m)  # a shared room's other drones, flight frame
        # Fused frames the flight map holds: the session's count, against map.frames_integrated.
        self.map_frames = 0
        self.event_counts: dict[str, int] = {}  # drone events so far, by kind
        self.errors = 0  # flight steps that raised
        self.fault: str | None = None  # why the drone was stopped for good, if it was
        self._failed_steps = RateLimitedLog(self.log)
        self._last_state: DroneUpdate | None = None
        # Every flight recorded (flight_recording.py, flight_records.py; ``recorder``: set later).
        self.records = FlightRecords(self._recording_failed)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    @property
    def spawned(self) -> bool:
        return self.sim.spawned

    @property
    def recorder(self) -> FlightRecorder | None:
        """The session's flight recorder (None: flights are not recorded)."""
        return self.records.recorder

    @recorder.setter
    def recorder(self, recorder: FlightRecorder | None) -> None:
        self.records.recorder = recorder

    # ------------------------------------------------------------------ frames
    @property
    def lock(self) -> threading.Lock:
        """The one lock over the simulator, its flight map and the course (CourseFlight)."""
        return self._lock

    def to_world(self, p_flight: np.ndarray) -> np.ndarray:
        """Flight-frame points ((3,) or (N, 3)) in the client's world."""
        return self.view.to_world(p_flight)

    def direction_to_world(self, v_flight: np.ndarray) -> np.ndarray:
        """Flight-frame directions or velocities ((3,) or (N, 3)) in the client's world."""
        return self.view.direction_to_world(v_flight)

    def world_corrected(self, T_correction: np.ndarray) -> None:
        """The tracker moved into a corrected world (loop closure; the client was sent
        map_corrected): T_correction (4x4, metres) maps the old world into the new one. The drone
        is reported in the new world from now on, while it still flies the old map until
        ``map_replaced`` brings the rebuilt one. The recent camera frames move with the
        world too (a tap on a frame from before the correction still lands where it showed).
        Tracking-thread side."""
        self.frames.move_with_world(T_correction)
        self.view.tracker_corrected(T_correction)

    # ------------------------------------------------------------------ inputs
    def camera_moved(self, seq: int, T_world_camera: np.ndarray, depth: np.ndarray) -> None:
        """A processed frame: its pose (and depth, for tapped pixels). Tracking-thread side."""
        self.frames.add(seq, T_world_camera, depth)

    def others_moved(self, centres: np.ndarray, velocities: np.ndarray) -> None:
        """The room's other drones as last heard of (world frame, ``FlightView.motion_in_
        flight``): this drone touches them (other_drones.py)."""
        with self._lock:
            self.others.set(*self.view.motion_in_flight(centres, velocities), time.monotonic())

    def map_changed(self, origin: np.ndarray, occupied: np.ndarray, observed: np.ndarray) -> None:
        """A new whole occupancy grid in the flight frame (``TSDFMap.occupancy(voxel_m,
        R_grid_world=R_flight_world)``); it replaces whatever is pending, and the flight thread
        applies it."""
        self.pending.grid(origin, occupied, observed)

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
        self.pending.replaced((origin, occupied, observed), T_correction, frames)

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
        self.pending.region(Region.whole(origin, occupied, observed), frames)

    def map_includes(self, frames: int) -> None:
        """The frames fused since the last update changed nothing the drone's grid holds: the
        flight map holds ``frames`` fused frames once what is pending is applied."""
        self.pending.frames(frames)

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
            target = self.frames.pixel_target(pixel, seq)
        with self._lock:
            carry_out(
                self.sim,
                self.view,
                name,
                command_id,
                target=target,
                sticks=sticks,
                speed=speed,
                flight_mode=flight_mode,
            )
            now_s = self.sim.time_s if self.spawned else 0.0
        self.records.command(now_s, name, command_id, asked)

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
            self.records.step(notices, state)

    def record_course(self, message: dict) -> None:
        """Attach a ``course`` message's course to the flight being recorded (FlightRecords.
        course; CourseFlight). Called with each course message sent (under the flight's lock
        only for a start or a stop, which write nothing to disk)."""
        self.records.course(message)

    def _recording_failed(self, what: str) -> None:
        """From an ``except`` block: a recording failed; counted and logged, the flight goes on."""
        self.errors += 1
        self._failed_steps.failure(what)

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
            DroneEventKind.FAULTED,
            final.timestamp,
            final.T_world_drone[:3, 3],
            f"the drone's simulation failed and the drone is stopped ({reason}); "
            "create a new session to fly again",
            None,
        )
        self.publish(notice)
        self.publish(final)
        self.records.step([notice], final)

    def _tick(self, dt: float) -> list[DroneNotice | dict]:
        """One flight step: the pending map changes, the physics for ``dt`` seconds, the
        course's judgement; returns what to publish."""
        with self._lock:
            events = []
            changes = self.pending.take()
            if changes.world is not None:
                grid, T_move = changes.world
                T_delta = self.view.flight_delta(T_move)
                self.sim.move_with_world(T_delta, *grid)
                self.course.move_with_world(T_delta)
                self.view.simulation_moved(T_move)
                self.corrections += 1
            if changes.grid is not None:
                self.sim.update_map(*changes.grid)
            if changes.region is not None:
                self.sim.update_map_region(changes.region)
            if changes.frames is not None:
                self.map_frames = changes.frames
            if changes.map_changed:
                if not self.spawned and (camera := self.frames.latest()) is not None:
                    self._spawn(camera[1])
            course = []
            if self.spawned:
                self.sim.set_others(self.others.at(time.monotonic()))
                events = self.sim.advance(dt)
                course = self.course.tick(events)  # gate notices and course messages
        notices = [self._notice(e) for e in events] + course
        for n in notices:
            if isinstance(n, DroneNotice):
                kind = n.event.value  # counted by the protocol's name (status: flight.events)
                self.event_counts[kind] = self.event_counts.get(kind, 0) + 1
        return notices

    def _spawn(self, T: np.ndarray) -> None:
        """Hover spawn_ahead_m in front of the camera, facing away from it, in observed free
        space; next to the camera when the space ahead is not known yet."""
        forward = invert(self.view.T_world_flight_shown())[:3, :3] @ T[:3, 2]
        yaw = float(np.arctan2(forward[1], forward[0]))
        for near in (T[:3, 3] + self.spawn_ahead_m * T[:3, 2], T[:3, 3]):
            try:
                self.sim.spawn(self.view.to_flight(near), yaw_rad=yaw)
                return
            except DroneCommandError:
                continue

    def _notice(self, event) -> DroneNotice:
        return DroneNotice(
            event.kind,
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
            T_world_flight = self.view.T_world_flight_shown()
        camera = self.frames.latest()
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
        with self._lock:  # from one flight step: the map it took, and whether it spawned
            map_frames, spawned = self.map_frames, self.spawned
        health = {
            "errors": self.errors,
            "fault": self.fault,
            "map_frames": map_frames,
            "corrections": self.corrections,
        }
        s = self.state() if spawned or self.fault is not None else None
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
