"""Gauss-Newton on SE(3) with fixed correspondences (eqs. 7-9)."""

from __future__ import annotations

import numpy as np

from server.geometry import Intrinsics, invert, rotation_angle_deg
from server.registration.config import RegistrationConfig, SolverConfig
from server.registration.sparse import point_information, scaled_condition, solve_sparse
from tests.conftest import random_pose

K = Intrinsics(525.0, 525.0, 319.5, 239.5, 640, 480)
DEPTH_CFG = RegistrationConfig().depth


def scene_points(rng, n=300):
    """Points in front of a camera, 0.8-4 m away, spread over the field of view."""
    z = rng.uniform(0.8, 4.0, n)
    u, v = rng.uniform(0, 640, n), rng.uniform(0, 480, n)
    return np.stack([(u - K.cx) * z / K.fx, (v - K.cy) * z / K.fy, z], axis=1)


def pose_error(T_est, T_true):
    E = invert(T_true) @ T_est
    return np.linalg.norm(E[:3, 3]), rotation_angle_deg(E)


def solve_from_identity(P: np.ndarray, Q: np.ndarray):
    """Sparse Gauss-Newton for P ~ T Q from T = I, each point with its sensor noise model."""
    return solve_sparse(
        P,
        Q,
        point_information(P, K, DEPTH_CFG),
        point_information(Q, K, DEPTH_CFG),
        np.eye(4),
        SolverConfig(),
    )


def test_exact_correspondences_recover_the_transform_from_identity():
    rng = np.random.default_rng(1)
    T_true = random_pose(rng, max_angle_rad=0.3, max_t_m=0.3)  # T_keyframe_current
    Q = scene_points(rng)
    P = Q @ T_true[:3, :3].T + T_true[:3, 3]
    sol = solve_from_identity(P, Q)
    dt, dr = pose_error(sol.T, T_true)
    assert dt < 1e-7 and dr < 1e-5
    assert sol.inliers.all()
    assert sol.rmse < 1e-4


def test_thirty_percent_outliers_are_rejected_and_the_pose_survives():
    rng = np.random.default_rng(2)
    T_true = random_pose(rng, max_angle_rad=0.15, max_t_m=0.1)
    Q = scene_points(rng, 400)
    P = Q @ T_true[:3, :3].T + T_true[:3, 3]
    P += rng.normal(scale=0.002, size=P.shape)  # sensor noise, 2 mm
    bad = rng.random(len(P)) < 0.3
    P[bad] += rng.uniform(-0.5, 0.5, size=(bad.sum(), 3))  # wrong LK matches
    sol = solve_from_identity(P, Q)
    dt, dr = pose_error(sol.T, T_true)
    assert dt < 0.002 and dr < 0.1
    # Nearly every planted outlier is flagged, and nearly every good match is kept.
    assert (~sol.inliers[bad]).mean() > 0.95
    assert sol.inliers[~bad].mean() > 0.9


def test_collinear_correspondences_are_flagged_as_degenerate():
    rng = np.random.default_rng(3)
    t = rng.uniform(-1, 1, 200)
    Q = np.stack(
        [t, 0.2 * t, np.full_like(t, 2.0)], axis=1
    )  # all on one line: roll about it is free
    P = Q + np.array([0.01, 0.0, 0.0])
    sol = solve_from_identity(P, Q)
    assert sol.condition < RegistrationConfig().state.min_condition


def test_scaled_condition_is_high_for_a_well_spread_scene():
    rng = np.random.default_rng(4)
    Q = scene_points(rng)
    sol = solve_from_identity(Q, Q)
    assert sol.condition > 100 * RegistrationConfig().state.min_condition
    assert scaled_condition(np.zeros((6, 6)), 1.0) == 0.0
