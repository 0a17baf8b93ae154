"""A pilot command's input checked and turned into numbers, and the mode a command needs.

``DroneSimulator`` calls these before it changes anything, so a bad command raises
DroneCommandError (the protocol's bad_command) and leaves the drone as it was. Points are in the
flight frame (metres, z up).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

from server.geometry.arrays import FloatArray
from server.simulation.config import SimulationConfig
from server.simulation.drone_types import DroneCommandError, DroneMode
from server.simulation.flight_map import FlightMap
from server.simulation.pilot_modes import FlightMode

Sticks = tuple[float, float, float, float]  # throttle, yaw, pitch, roll in -1..1
CENTRED: Sticks = (0.0, 0.0, 0.0, 0.0)


def checked_point(value: ArrayLike, what: str) -> FloatArray:
    """``value`` as a (3,) point; raises DroneCommandError unless it is 3 finite numbers."""
    try:
        p = np.asarray(value, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        p = np.empty(0)
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        raise DroneCommandError(f"{what} must be 3 finite numbers, got {value!r}")
    return p


def goto_speed(speed: float | None, config: SimulationConfig) -> float:
    """A goto's speed (m/s): cruise speed when None, capped at max_speed_m_s."""
    speed = config.cruise_speed_m_s if speed is None else float(speed)
    if not math.isfinite(speed) or speed <= 0:
        raise DroneCommandError(f"goto speed must be a positive number, got {speed}")
    return min(speed, config.max_speed_m_s)


def checked_sticks(values: ArrayLike, deadband: float) -> Sticks:
    """``[throttle, yaw, pitch, roll]`` clipped to -1..1, zero within ``deadband`` (applied
    once here, not on every physics step)."""
    raw = np.asarray(values, dtype=float).reshape(-1)
    if raw.shape != (4,) or not np.all(np.isfinite(raw)):
        raise DroneCommandError("sticks must be 4 finite numbers [throttle, yaw, pitch, roll]")
    throttle, yaw, pitch, roll = (
        0.0 if abs(v) <= deadband else float(v) for v in np.clip(raw, -1.0, 1.0)
    )
    return throttle, yaw, pitch, roll


def checked_flight_mode(mode: str) -> FlightMode:
    """The FlightMode named ``mode``; an unknown name raises DroneCommandError."""
    try:
        return FlightMode(mode)
    except ValueError:
        choices = ", ".join(m.value for m in FlightMode)
        raise DroneCommandError(f"flight_mode must be one of {choices}; got {mode!r}") from None


def require_spawned(mode: DroneMode | None) -> DroneMode:
    """The mode; raises DroneCommandError before spawn (``mode`` None)."""
    if mode is None:
        raise DroneCommandError("no drone yet: it spawns with the first map")
    return mode


def require_flying(mode: DroneMode | None, what: str) -> None:
    """Raises DroneCommandError unless the drone is in the air under power."""
    mode = require_spawned(mode)
    if mode == DroneMode.LANDED:
        raise DroneCommandError(f"{what} needs a flying drone; it is landed (take off first)")
    if mode == DroneMode.CRASHED:
        raise DroneCommandError(
            f"{what} needs a flying drone; it crashed and is falling (take off again once "
            "it has landed)"
        )


def takeoff_height(flight_map: FlightMap, start: FloatArray, config: SimulationConfig) -> float:
    """How far (m) a drone landed at ``start`` rises: up to takeoff_height_m through
    sphere-free space, to the highest point there with planning clearance; raises
    DroneCommandError when there is none."""
    step = config.voxel_m / 2
    heights = np.arange(step, config.takeoff_height_m + 1e-9, step)
    clear = flight_map.distance(start + heights[:, None] * [0.0, 0.0, 1.0])
    touching = clear < config.radius_m
    reachable = heights[: int(np.argmax(touching)) if touching.any() else len(heights)]
    good = reachable[clear[: len(reachable)] >= config.planning_radius_m]
    if len(good) == 0:
        raise DroneCommandError("no room above the drone to take off")
    return float(good[-1])
