"""A planned route and why there is none: the planner's answer, in the flight frame (metres, z up).

``Route`` is what ``plan_path`` and ``timed_route`` (planner.py) return and what the drone's
``RouteTracker`` (control.py) flies; ``PlanningError`` (with a ``Reason``) is their refusal.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum

import numpy as np

from server.errors import DroneSimError
from server.geometry.arrays import FloatArray, RealArray


class Reason(str, Enum):
    """Why no route was found; compares equal to its string value."""

    GOAL_BLOCKED = "goal_blocked"
    START_BLOCKED = "start_blocked"
    UNREACHABLE = "unreachable"
    OUTSIDE_MAP = "outside_map"
    NOT_FINITE = "not_finite"


class PlanningError(DroneSimError):
    """No route. ``reason``: a ``Reason``; ``nearest``: (3,) the free point nearest to the goal
    that a route from the start reaches (for ``start_blocked``: the free point nearest to the
    start), or None when there is none."""

    def __init__(self, reason: Reason, message: str, nearest: np.ndarray | None = None):
        super().__init__(message)
        self.reason = Reason(reason)
        self.nearest = None if nearest is None else np.asarray(nearest, dtype=np.float64)


@dataclass
class Route:
    """A timed route. ``points`` (N, 3): the shortcut polyline (start, corners, goal); ``path``
    (M, 3): the smoothed curve the drone follows, sampled densely, with ``times`` (M,) s and
    ``speeds`` (M,) m/s at each sample. Every path sample and ``points`` segment was checked
    against the map at the planning clearance."""

    points: FloatArray
    path: FloatArray
    times: FloatArray
    speeds: FloatArray
    length_m: float
    duration_s: float
    _tangents: FloatArray = field(repr=False)
    _curvatures: FloatArray = field(repr=False)  # curvature vectors kappa * normal, 1/m

    def sample(self, t_s: float | RealArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """(position, velocity, acceleration) at time ``t_s`` (clamped to the route): (3,) each
        for a scalar time, (K, 3) each for K times. Speed along the path changes with constant
        acceleration between samples."""
        t = np.clip(np.asarray(t_s, dtype=np.float64), 0.0, self.duration_s)
        scalar = t.ndim == 0
        t = t.reshape(-1)
        if len(self.path) == 1:
            zeros = np.zeros((len(t), 3))
            position: FloatArray = np.repeat(self.path, len(t), axis=0)
            return _first_if(scalar, position, zeros, zeros.copy())
        i = np.clip(np.searchsorted(self.times, t, side="right") - 1, 0, len(self.path) - 2)
        ds = np.linalg.norm(self.path[i + 1] - self.path[i], axis=1)
        v0, v1 = self.speeds[i], self.speeds[i + 1]
        accel = (v1**2 - v0**2) / (2 * np.maximum(ds, 1e-12))
        tau = t - self.times[i]
        speed = np.clip(v0 + accel * tau, 0.0, np.maximum(v0, v1))
        frac = np.clip((v0 * tau + 0.5 * accel * tau**2) / np.maximum(ds, 1e-12), 0.0, 1.0)
        f = frac[:, None]
        position = self.path[i] + f * (self.path[i + 1] - self.path[i])
        tangent = (1 - f) * self._tangents[i] + f * self._tangents[i + 1]
        tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-12)
        curvature = (1 - f) * self._curvatures[i] + f * self._curvatures[i + 1]
        velocity = speed[:, None] * tangent
        acceleration = accel[:, None] * tangent + (speed**2)[:, None] * curvature
        return _first_if(scalar, position, velocity, acceleration)


def _first_if(
    scalar: bool, position: FloatArray, velocity: FloatArray, acceleration: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Route.sample's result: the (K, 3) arrays, or their first rows for a scalar time."""
    if scalar:
        return position[0], velocity[0], acceleration[0]
    return position, velocity, acceleration


def fmt_point(p: FloatArray) -> str:
    """A point for an error message: ``(x, y, z)``, metres, two decimals."""
    return "(" + ", ".join(f"{x:.2f}" for x in np.asarray(p).reshape(-1)) + ")"
