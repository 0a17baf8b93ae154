"""Contact with the map: physics steps checked against the distance field, and what a touch does.

Flight frame, metres, z up. The drone is a sphere of ``radius_m`` and touches the map when the
distance field at its centre drops below the radius. The field is 1-Lipschitz, so a chunk of
steps whose travelled length is provably shorter than the clearance at its start needs no query
per step; near obstacles a few steps are run, then every one of them is checked (in plain
floats, ``FlightMap.distance_at``: cheaper than numpy for a chunk's few points), rewinding to the
step before a contact (``run_checked``). A step moves at most
max_speed / physics_hz (< radius, checked by the config), so the sphere cannot jump over a wall
between two checks (the swept segment is covered), and ``segments_free`` guards longer steps.

A touch is judged by its speed along the surface normal (the distance field's gradient where
the drone touched; ``touch``): at ``crash_speed_m_s`` or more it is a **crash** (motors off, a
small bounce and a tumble: it falls); below it a **bump**: back to the last collision-free
position (a little off the surface) with the normal velocity reflected (times
``bump_restitution``) and the speed along the surface damped (``bump_friction``). A crashed,
falling drone that touches the map **rests** there when that is ground below it or it is
nearly still, else it **slides** off (bounced the same way). What each means for the drone's
mode, setpoint, damage and events is the modes' part (modes.py); the helpers at the end serve
it: a held position moved off the surface after a bump (``hold_off_surface``), one collision
event a second at one place (``CollisionReports``), and the way out when the map grew into the
drone (``leave_obstacle``).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from enum import Enum
from typing import Protocol, TypeVar

import numpy as np
from numpy.typing import ArrayLike

from server.geometry.arrays import BoolArray, FloatArray
from server.simulation.config import SimulationConfig
from server.simulation.control import Setpoint
from server.simulation.flight_map import FlightMap
from server.simulation.quadrotor import Quadrotor

log = logging.getLogger(__name__)

LIPSCHITZ_SAFETY = 1.5  # the interpolated distance field may change faster than 1 m per metre
MAX_CHUNK_STEPS = 100  # physics steps between distance queries far from obstacles
NEAR_CHUNK_STEPS = 16  # near obstacles, steps checked together in one query
BUMP_STANDOFF_M = 0.01  # a bump puts the drone this far off the surface (resting contacts)
CRASH_TUMBLE_RAD_S = 4.0  # a crashed drone tumbles at this rate while it falls
CRASH_REST_NORMAL_Z = 0.5  # a crashed drone rests on a surface whose normal is this far up
CRASH_REST_SPEED_M_S = 0.3  # ... or on any surface once slower than this
# A drone pushed against a wall touches it again and again: one collision event per second
# at the same place (the stop itself happens every time).
COLLISION_REPEAT_S = 1.0
COLLISION_REPEAT_M = 0.05


S = TypeVar("S")  # what a Stepper saves for rewinding


class DistanceField(Protocol):
    """What contact asks of the space the drone flies in: a ``FlightMap``, or one with the
    room's other drones in it (other_drones.py ``WithDrones``)."""

    def distance_at(self, x: float, y: float, z: float) -> float: ...

    def distance(self, points: ArrayLike) -> FloatArray: ...

    def gradient(self, points: ArrayLike) -> FloatArray: ...

    def segments_free(self, a: ArrayLike, b: ArrayLike, radius_m: float = 0.0) -> BoolArray: ...


class Stepper(Protocol[S]):
    """What ``run_checked`` drives: the simulator's physics steps and their rewinding."""

    def resting(self) -> bool:
        """Whether the drone sits still on the map (no step can touch anything)."""
        ...

    def step(self) -> None:
        """Mode logic, controller and one physics step (simulation time moves on by dt)."""
        ...

    def wait(self, n: int) -> None:
        """Let ``n`` steps pass without physics (the drone rests)."""
        ...

    def save(self) -> S:
        """What a step may change, for ``restore``."""
        ...

    def restore(self, saved: S) -> None: ...

    def contact(self, last_free: FloatArray) -> None:
        """The step after ``last_free`` touched the map (its time already counted)."""
        ...


def run_checked(
    stepper: Stepper[S],
    q: Quadrotor,
    flight_map: DistanceField,
    config: SimulationConfig,
    a_max_m_s2: float,
    n: int,
) -> None:
    """Run ``n`` physics steps of ``stepper`` (whose drone is ``q``) with every step checked
    against ``flight_map`` (module docstring); ``a_max_m_s2`` bounds the drone's acceleration.
    The simulation is deterministic, so a contact found after a chunk is replayed exactly up
    to the step before it."""
    dt = config.dt_s
    radius = config.radius_m
    while n > 0:
        if stepper.resting():
            stepper.wait(n)
            return
        here = (q.px, q.py, q.pz)
        clearance = flight_map.distance_at(q.px, q.py, q.pz)
        budget = (clearance - radius - config.voxel_m) / LIPSCHITZ_SAFETY
        if budget > 0:
            # Far from the map: steps whose travel |v| t + a_max t^2 / 2 stays within the
            # budget cannot touch it; no query needed.
            v = math.sqrt(q.vx * q.vx + q.vy * q.vy + q.vz * q.vz)
            t = (math.sqrt(v * v + 2 * a_max_m_s2 * budget) - v) / a_max_m_s2
            k = min(n, MAX_CHUNK_STEPS, int(t / dt))
            if k > 0:
                for _ in range(k):
                    stepper.step()
                n -= k
                continue
        # Near the map: run a few steps, then check each of them in one query; on contact,
        # rewind and replay up to the step before it.
        k = min(n, NEAR_CHUNK_STEPS)
        saved = stepper.save()
        track = [here]
        for _ in range(k):
            stepper.step()
            track.append((q.px, q.py, q.pz))
        j = first_contact(flight_map, track, radius)
        if j is None:
            n -= k
            continue
        stepper.restore(saved)
        for _ in range(j):
            stepper.step()
        stepper.wait(1)  # the step that touched
        stepper.contact(np.array(track[j]))
        n -= j + 1


def first_contact(
    flight_map: DistanceField, track: Sequence[tuple[float, float, float]], radius_m: float
) -> int | None:
    """Index of the first step of ``track`` (k + 1 positions (x, y, z), metres) that touches
    the map, or None. Inside an obstacle (the map grew into the drone) it may move out, never
    deeper. Plain floats, point by point (``FlightMap.distance_at``): for the few positions of
    a chunk that is several times cheaper than numpy's per-call cost, and gives the same
    distances to the bit."""
    distance_at = flight_map.distance_at
    x0, y0, z0 = track[0]
    d0 = distance_at(x0, y0, z0)
    long_m = 0.5 * radius_m
    for j in range(1, len(track)):
        x1, y1, z1 = track[j]
        d1 = distance_at(x1, y1, z1)
        if d1 < radius_m and d1 < d0:
            return j - 1
        dx, dy, dz = x1 - x0, y1 - y0, z1 - z0
        long = math.sqrt(dx * dx + dy * dy + dz * dz) > long_m  # never at the configured limits
        if long and not _swept_free(flight_map, (x0, y0, z0), (x1, y1, z1), radius_m):
            return j - 1
        x0, y0, z0, d0 = x1, y1, z1, d1
    return None


def _swept_free(
    flight_map: DistanceField,
    a: tuple[float, float, float],
    b: tuple[float, float, float],
    radius_m: float,
) -> bool:
    """Whether the sphere swept along a step from ``a`` to ``b`` that is too long to check by
    its ends alone stays free."""
    return bool(flight_map.segments_free(np.array([a]), np.array([b]), radius_m)[0])


class Touch(str, Enum):
    """What a contact with the map was (module docstring)."""

    BUMP = "bump"
    CRASH = "crash"
    REST = "rest"  # a crashed drone came to rest
    SLIDE = "slide"  # a crashed drone slid off


@dataclass(frozen=True)
class Contact:
    """A judged touch: ``position`` (3,) where the drone was put back (flight frame, m),
    ``normal`` (3,) the surface's unit normal there, ``impact_m_s`` the speed into it."""

    kind: Touch
    position: FloatArray
    normal: FloatArray
    impact_m_s: float


def touch(
    q: Quadrotor,
    flight_map: DistanceField,
    config: SimulationConfig,
    last_free: FloatArray,
    crashed: bool,
) -> Contact:
    """Judge the touch of a drone that was last free at ``last_free`` and is now at ``q``
    (``crashed``: falling with its motors off), and move ``q`` as it makes it move."""
    v = np.array([q.vx, q.vy, q.vz])
    normal = surface_normal(flight_map, last_free, v)
    v_n = float(v @ normal)  # negative: towards the surface
    impact = max(0.0, -v_n)
    if crashed:
        if normal[2] >= CRASH_REST_NORMAL_Z or float(np.linalg.norm(v)) < CRASH_REST_SPEED_M_S:
            q.reset(last_free, q.yaw_rad, hovering=False)
            return Contact(Touch.REST, last_free, normal, impact)
        _put(q, last_free, bounced(v, normal, v_n, config))
        return Contact(Touch.SLIDE, last_free, normal, impact)
    if impact >= config.crash_speed_m_s:
        _put(q, last_free, bounced(v, normal, v_n, config))
        q.f0 = q.f1 = q.f2 = q.f3 = 0.0
        # Tumble about the horizontal axis along the surface (body frame), a fixed rate.
        axis = np.cross([0.0, 0.0, 1.0], normal)
        if float(np.linalg.norm(axis)) < 1e-6:
            axis = np.array([1.0, 0.0, 0.0])
        axis = q.R_flight_body.T @ (axis / np.linalg.norm(axis))
        q.wx, q.wy, q.wz = (float(c) for c in CRASH_TUMBLE_RAD_S * axis)
        return Contact(Touch.CRASH, last_free, normal, impact)
    # A little off the surface, so that a drone pushed on against it (resting contact)
    # touches again after some steps, not at every one (each contact rewinds a chunk).
    off_surface = last_free + BUMP_STANDOFF_M * normal
    d_from, d_to = flight_map.distance(np.stack([last_free, off_surface]))
    if d_to > d_from:
        last_free = off_surface
    _put(q, last_free, bounced(v, normal, v_n, config))
    return Contact(Touch.BUMP, last_free, normal, impact)


def surface_normal(flight_map: DistanceField, where: FloatArray, v: FloatArray) -> FloatArray:
    """Unit normal of the map's surface nearest to ``where`` (the distance field's gradient,
    pointing away from it); against the velocity ``v`` where the field is flat."""
    g = flight_map.gradient(where[None])[0]
    n = float(np.linalg.norm(g))
    if n > 1e-6:
        return np.asarray(g / n, dtype=float)
    speed = float(np.linalg.norm(v))
    return -v / speed if speed > 1e-9 else np.array([0.0, 0.0, 1.0])


def bounced(v: FloatArray, normal: FloatArray, v_n: float, config: SimulationConfig) -> FloatArray:
    """Velocity ``v`` (m/s) after a bounce off a surface of unit ``normal`` (``v_n``: v's
    normal part): the normal part reflected and damped, the tangential part slowed."""
    tangential = v - v_n * normal
    out: FloatArray = (1.0 - config.bump_friction) * tangential
    return out - config.bump_restitution * v_n * normal


def _put(q: Quadrotor, position: FloatArray, velocity: FloatArray) -> None:
    q.px, q.py, q.pz = (float(c) for c in position)
    q.vx, q.vy, q.vz = (float(c) for c in velocity)


def hold_off_surface(
    sp: Setpoint, flight_map: FlightMap, off: FloatArray, clearance_m: float
) -> None:
    """After a bump: a position ``sp`` holds closer than ``clearance_m`` to the map moves to
    ``off`` (3,) (off the surface it touched) on the axes it holds, so that holding it does
    not push the drone into the wall again."""
    held = np.array([sp.x, sp.y, sp.z])
    if float(flight_map.distance(held[None])[0]) < clearance_m:
        if sp.hold_xy:
            sp.x, sp.y = float(off[0]), float(off[1])
        if sp.hold_z:
            sp.z = float(off[2])


class CollisionReports:
    """When a bump is worth a ``collision`` event: not within COLLISION_REPEAT_S and
    COLLISION_REPEAT_M of the last one told."""

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self._last: tuple[float, FloatArray] = (-math.inf, np.zeros(3))  # time, position

    def due(self, time_s: float, where: FloatArray) -> bool:
        """Whether a bump at ``where`` (3,) at ``time_s`` is told; if so it is the last."""
        t_last, p_last = self._last
        if (
            time_s - t_last > COLLISION_REPEAT_S
            or np.linalg.norm(where - p_last) > COLLISION_REPEAT_M
        ):
            self._last = (time_s, where)
            return True
        return False

    def move_with_world(self, R: FloatArray, t: FloatArray) -> None:
        """The last bump's place moves with a corrected world (``R`` (3, 3), ``t`` (3,) m)."""
        self._last = (self._last[0], R @ self._last[1] + t)


def free_point_near(flight_map: FlightMap, point: FloatArray, radius_m: float) -> FloatArray | None:
    """``point`` itself when its clearance is ``radius_m`` or more, else the nearest free
    cell centre (None when there is none)."""
    if float(flight_map.distance(point[None])[0]) >= radius_m:
        return np.array(point)  # a copy
    free = flight_map.nearest_free(point, radius_m)
    return None if free is None else np.asarray(free, dtype=float)


def leave_obstacle(q: Quadrotor, flight_map: FlightMap, config: SimulationConfig) -> bool:
    """If the map grew into the drone at ``q``, put it, level and hovering, at the nearest
    point with planning clearance; whether it moved."""
    position = q.position
    if float(flight_map.distance(position[None])[0]) >= config.radius_m:
        return False
    free = free_point_near(flight_map, position, config.planning_radius_m)
    if free is None:
        log.warning("the map grew into the drone at %s and no free space is near", position)
        return False
    q.reset(np.asarray(free, dtype=float), q.yaw_rad, hovering=True)
    return True
