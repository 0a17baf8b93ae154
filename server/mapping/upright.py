"""Which way is up in a map: the rotation from the world frame into an upright frame.

The world frame is that of the poses (``T_world_camera``, metres); a live session's is its first
camera's (x right, y down, z forward), an offline run's may be a ground truth's. The upright frame
has the same origin, z up against gravity and x the first camera's optical axis made level (so y is
to its left): the drone's flight frame (server/sessions/runtime/flight.py), and the convention of
Blender, MeshLab and ROS. ``R_upright_world`` (3x3) maps world coordinates into it.

Up comes from the best source there is (``UpSource``): gravity, when a phone measured it; else
the map's horizontal surfaces (floors, desk and table tops, whose normals dominate those near the
first camera's up); else the first camera's up (-y) alone, as if it had been held level.
Pure numpy: no Open3D, no files.
"""

from __future__ import annotations

import logging
from enum import Enum

import numpy as np
from numpy.typing import ArrayLike

from server.geometry.arrays import FloatArray

log = logging.getLogger(__name__)

CAMERA_UP = np.array([0.0, -1.0, 0.0])  # a level camera's up, in its own axes (y down)
CAMERA_FORWARD = np.array([0.0, 0.0, 1.0])  # its optical axis
# Surfaces further than this from the first camera's up are not floors: a camera pitched down
# at a desk by up to ~45 degrees (TUM fr1/xyz: 38) still finds it; a wall facing the camera
# is 90 degrees plus the pitch away (its normal points back at the camera).
MAX_TILT_DEG = 50.0
MIN_AREA_M2 = 0.1  # horizontal surface needed to trust it over the camera (a small desk top)
# Coarse to fine: the mean of the normals within each window of the estimate so far, so that a
# large floor wins over a few sloped patches that the widest window also holds.
_WINDOWS_DEG = (MAX_TILT_DEG, 25.0, 10.0, 5.0)


class UpSource(str, Enum):
    """Where an upright frame's up came from."""

    GRAVITY = "gravity"  # the phone's gravity
    SURFACES = "surfaces"  # the map's horizontal surfaces
    CAMERA = "camera"  # the first camera's -y


def _unit(v: ArrayLike, name: str) -> FloatArray:
    v = np.asarray(v, dtype=np.float64).reshape(3)
    n = float(np.linalg.norm(v))
    if not np.isfinite(n) or n < 1e-9:
        raise ValueError(f"{name} must be a finite non-zero 3-vector, got {v}")
    return v / n


def upright_rotation(up_world: ArrayLike, forward_world: ArrayLike) -> FloatArray:
    """R_upright_world (3x3, a rotation): upright z along ``up_world``, upright x along
    ``forward_world`` made level (perpendicular to up); when forward is (nearly) vertical, the
    world's x axis made level is taken instead. Both are directions in the world frame."""
    up = _unit(up_world, "up")
    for forward in (_unit(forward_world, "forward"), np.array([1.0, 0.0, 0.0])):
        x = forward - forward.dot(up) * up
        if np.linalg.norm(x) > 1e-3:
            break
    else:  # up is the world's x and forward is vertical: any level axis will do
        x = np.array([0.0, 1.0, 0.0]) - up[1] * up
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(up, x), up])


def triangle_normals(vertices: ArrayLike, triangles: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Per triangle: unit normal (M, 3), by the winding's right-hand rule, and area (M,) m^2.
    vertices (N, 3) metres, triangles (M, 3) vertex indices. Degenerate triangles get a zero
    normal and zero area."""
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    t = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    cross = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
    twice_area = np.linalg.norm(cross, axis=1)
    normals = np.divide(cross, twice_area[:, None], out=np.zeros_like(cross),
                        where=twice_area[:, None] > 0)  # fmt: skip
    return normals, twice_area / 2


def up_from_surfaces(
    vertices: ArrayLike,
    triangles: ArrayLike,
    prior_up: ArrayLike,
    max_tilt_deg: float = MAX_TILT_DEG,
    min_area_m2: float = MIN_AREA_M2,
) -> FloatArray | None:
    """Up (unit, world frame) as the normal of the mesh's dominant horizontal surfaces, or
    None when less than ``min_area_m2`` of surface faces within ``max_tilt_deg`` of
    ``prior_up`` (a direction in the world frame, e.g. the first camera's -y).

    The triangles must wind so that their normals point out of the surface into the space
    seen empty, as marching cubes over a TSDF makes them: a floor's point up, a ceiling's
    down (not counted), a wall's back towards the camera. The estimate is the area-weighted
    mean normal within windows of 50, 25, 10 and 5 degrees of the estimate before (none
    further than ``max_tilt_deg`` from the prior), so the largest flat area decides.
    """
    prior = up = _unit(prior_up, "prior_up")
    normals, areas = triangle_normals(vertices, triangles)
    for window in (min(w, max_tilt_deg) for w in _WINDOWS_DEG):
        near = (normals @ up >= np.cos(np.radians(window))) & (
            normals @ prior >= np.cos(np.radians(max_tilt_deg))
        )
        if areas[near].sum() < min_area_m2:
            return None
        up = _unit(areas[near] @ normals[near], "surface normal")
    return up


def upright_frame(
    T_world_camera0: ArrayLike,
    vertices: ArrayLike | None = None,
    triangles: ArrayLike | None = None,
    gravity_world: ArrayLike | None = None,
) -> tuple[FloatArray, UpSource]:
    """R_upright_world (3x3) and where its up came from, for a map whose first camera had the
    pose ``T_world_camera0`` (4x4, metres): up against ``gravity_world`` (a direction in the
    world frame) when given, else from the mesh's horizontal surfaces (``vertices`` (N, 3)
    metres, ``triangles`` (M, 3), world frame) near the camera's up, else the camera's up.
    Upright x is the first camera's optical axis, made level."""
    R_world_camera0 = np.asarray(T_world_camera0, dtype=np.float64)[:3, :3]
    forward = R_world_camera0 @ CAMERA_FORWARD
    if gravity_world is not None:
        return upright_rotation(-_unit(gravity_world, "gravity"), forward), UpSource.GRAVITY
    camera_up = R_world_camera0 @ CAMERA_UP
    if vertices is not None and triangles is not None:
        up = up_from_surfaces(vertices, triangles, camera_up)
        if up is not None:
            tilt = np.degrees(np.arccos(np.clip(up @ camera_up, -1.0, 1.0)))
            log.info("up from the map's horizontal surfaces, %.1f deg from the camera's", tilt)
            return upright_rotation(up, forward), UpSource.SURFACES
    log.info("no horizontal surfaces in the map: up is the first camera's -y")
    return upright_rotation(camera_up, forward), UpSource.CAMERA
