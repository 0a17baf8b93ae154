"""Gauss-Newton on SE(3) over fixed 3D-3D correspondences (paper, eqs. 7-9).

Each correspondence pairs a keyframe point p (keyframe camera frame) with a current-frame point
q (current camera frame); we look for T_keyframe_current minimising sum |p - T q|^2 in the
Mahalanobis metric of both points' sensor noise, with robust weights.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from server.geometry import Intrinsics, exp_se3, orthonormalize
from server.geometry.arrays import BoolArray, FloatArray
from server.registration.config import DepthConfig, SolverConfig
from server.registration.preprocess import axial_sigma


@dataclass
class NormalEquations:
    """J^T W J and J^T W r of one cost term at the current pose, ``xi = (omega, t)``."""

    H: FloatArray  # (6, 6)
    g: FloatArray  # (6,)

    def __add__(self, other: NormalEquations) -> NormalEquations:
        return NormalEquations(self.H + other.H, self.g + other.g)


@dataclass
class SparseSolution:
    """Result of :func:`solve_sparse`."""

    T: FloatArray  # T_keyframe_current, 4x4, metres
    inliers: BoolArray  # (N,)
    rmse: float  # Mahalanobis RMSE of the inliers (1.0 = residuals as large as the noise)
    condition: float  # smallest / largest eigenvalue of the scaled J^T W J
    iterations: int
    equations: NormalEquations  # of the inliers at the solution, for joint refinement


def point_information(points: FloatArray, K: Intrinsics, cfg: DepthConfig) -> FloatArray:
    """Covariances (N, 3, 3) in m^2 of back-projected points in their camera frame.

    Depth noise acts along the viewing ray and grows with z^2; a pixel error acts across the
    ray and grows with z. The two differ by an order of magnitude, so one isotropic sigma
    would over-trust depth or under-trust the image.
    """
    z = points[:, 2]
    ray = points / np.linalg.norm(points, axis=1, keepdims=True)
    s_axial = axial_sigma(z, cfg)
    s_lateral = z * cfg.lateral_noise_px / (0.5 * (K.fx + K.fy))
    outer = ray[:, :, None] * ray[:, None, :]
    eye = np.eye(3)[None]
    lateral: FloatArray = (s_lateral**2)[:, None, None] * (eye - outer)
    axial: FloatArray = (s_axial**2)[:, None, None] * outer
    return lateral + axial


def information(cov_P: FloatArray, cov_Q: FloatArray, R: FloatArray) -> FloatArray:
    """Information matrices (N, 3, 3) in 1/m^2 of r = p - T q: the inverse of cov_P + R cov_Q R^T,
    with cov_Q (current camera frame) rotated by R (of T_keyframe_current) into the keyframe."""
    return _inverse_3x3(cov_P + rotate_covariances(cov_Q, R))


def rotate_covariances(cov: FloatArray, R: FloatArray) -> FloatArray:
    """R cov R^T for (N, 3, 3) symmetric covariances, as two (3N, 3) x (3, 3) products: one
    BLAS call each, where a broadcast (3, 3) @ (N, 3, 3) @ (3, 3) loops per matrix (2.4x
    slower for 200 points)."""
    n = len(cov)
    cov_Rt = (cov.reshape(-1, 3) @ R.T).reshape(n, 3, 3)  # cov R^T; its transpose is R cov
    rotated: FloatArray = (cov_Rt.transpose(0, 2, 1).reshape(-1, 3) @ R.T).reshape(n, 3, 3)
    return rotated  # R cov R^T, symmetric like cov


def _inverse_3x3(M: FloatArray) -> FloatArray:
    """Inverses of (N, 3, 3) symmetric matrices by their adjugate (symmetric too): np.linalg.inv
    calls LAPACK once per matrix, several times slower for hundreds of 3x3 covariances (which
    are well conditioned). Only the upper triangle of each M is read."""
    a, b, c = M[:, 0, 0], M[:, 0, 1], M[:, 0, 2]
    e, f, i = M[:, 1, 1], M[:, 1, 2], M[:, 2, 2]
    c00, c01, c02 = e * i - f * f, c * f - b * i, b * f - c * e  # cofactors of the first row
    c11, c12, c22 = a * i - c * c, b * c - a * f, a * e - b * b
    det = a * c00 + b * c01 + c * c02
    adj = np.stack([c00, c01, c02, c01, c11, c12, c02, c12, c22], axis=1).reshape(-1, 3, 3)
    return adj / det[:, None, None]


def robust_equations(
    P: FloatArray, Q: FloatArray, W: FloatArray, T: FloatArray, cfg: SolverConfig, reject: bool
) -> tuple[NormalEquations, FloatArray, FloatArray]:
    """Normal equations of r = p - T q (information matrices W, (N, 3, 3)) with the Huber
    weights of the residuals' own Mahalanobis distances (``robust_weights``); also the
    distances (N,) and the weights (N,). The residuals are computed once for both."""
    y, Wr, distances = _residuals(P, Q, W, T)
    weights = robust_weights(distances, cfg, reject)
    return _normal_equations(y, W, Wr, weights), distances, weights


def _residuals(
    P: FloatArray, Q: FloatArray, W: FloatArray, T: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """y = T q (N, 3), W r (N, 3) and the Mahalanobis distances (N,) of r = p - y."""
    y = Q @ T[:3, :3].T + T[:3, 3]
    r = P - y
    Wr = np.einsum("nij,nj->ni", W, r)
    return y, Wr, np.sqrt(np.maximum(np.einsum("ni,ni->n", r, Wr), 0.0))


def _normal_equations(
    y: FloatArray, W: FloatArray, Wr: FloatArray, weights: FloatArray
) -> NormalEquations:
    """J^T w W J and J^T w W r over the points, from y = T q and W r (``_residuals``)."""
    # d r / d xi for the left perturbation T <- exp(xi) T: [ [y]_x , -I ].
    J = np.zeros((len(y), 3, 6))
    J[:, 0, 1], J[:, 0, 2] = -y[:, 2], y[:, 1]
    J[:, 1, 0], J[:, 1, 2] = y[:, 2], -y[:, 0]
    J[:, 2, 0], J[:, 2, 1] = -y[:, 1], y[:, 0]
    J[:, :, 3:] = -np.eye(3)
    # Sum over points of J^T w W J as one (3N, 6)^T (3N, 6) product: a multi-operand einsum
    # would loop in numpy's own kernel instead of BLAS.
    WJ = (W @ J) * weights[:, None, None]
    Jf = J.reshape(-1, 6)
    H = Jf.T @ WJ.reshape(-1, 6)
    g = Jf.T @ (Wr * weights[:, None]).reshape(-1)
    return NormalEquations(H, g)


def robust_weights(m: FloatArray, cfg: SolverConfig, reject: bool) -> FloatArray:
    """Huber weights on Mahalanobis distances; with ``reject``, outliers get weight 0."""
    w = np.where(m <= cfg.huber_k, 1.0, cfg.huber_k / np.maximum(m, 1e-12))
    if reject:
        w = np.where(m <= cfg.outlier_chi, w, 0.0)
    return w


def scaled_condition(H: FloatArray, scene_depth: float) -> float:
    """Conditioning of J^T W J with rotation expressed as metres of motion at the scene depth,
    so that rotation and translation are comparable; near 0 means a direction is unconstrained."""
    s = np.array([1.0 / scene_depth] * 3 + [1.0] * 3)
    eig = np.linalg.eigvalsh(H * s[:, None] * s[None, :])
    return float(max(eig[0], 0.0) / eig[-1]) if eig[-1] > 0 else 0.0


def solve_sparse(
    P: FloatArray,
    Q: FloatArray,
    cov_P: FloatArray,
    cov_Q: FloatArray,
    T_init: FloatArray,
    cfg: SolverConfig,
) -> SparseSolution:
    """Minimise eq. 7 by Gauss-Newton from ``T_init`` (T_keyframe_current).

    P, Q: (N, 3) corresponding points in the keyframe and current camera frames, metres.
    cov_P, cov_Q: (N, 3, 3) their covariances, m^2.
    The first iterations use Huber weights only, so that a poor initial guess cannot throw
    good correspondences away; then correspondences beyond ``outlier_chi`` are rejected.
    """
    T = T_init.copy()
    n = len(P)
    if n < 3:
        return SparseSolution(
            T, np.zeros(n, bool), np.inf, 0.0, 0, NormalEquations(np.zeros((6, 6)), np.zeros(6))
        )
    it = 0
    huber_only = max(2, cfg.max_iterations // 3)
    for it in range(1, cfg.max_iterations + 1):
        W = information(cov_P, cov_Q, T[:3, :3])
        eq, _, weights = robust_equations(P, Q, W, T, cfg, reject=it > huber_only)
        if not np.any(weights > 0):
            break
        xi = gauss_newton_step(eq.H, eq.g)
        # exp(xi) is a rotation to rounding: T is projected back onto SE(3) once, at the end.
        T = exp_se3(xi) @ T
        if np.linalg.norm(xi) < cfg.convergence_step and it > huber_only:
            break
    T = orthonormalize(T)
    W = information(cov_P, cov_Q, T[:3, :3])
    eq, m, _ = robust_equations(P, Q, W, T, cfg, reject=True)
    inliers = m <= cfg.outlier_chi
    rmse = float(np.sqrt(np.mean(m[inliers] ** 2))) if inliers.any() else np.inf
    depth = float(np.median(P[:, 2])) if n else 1.0
    return SparseSolution(T, inliers, rmse, scaled_condition(eq.H, depth), it, eq)


def gauss_newton_step(H: FloatArray, g: FloatArray) -> FloatArray:
    """The Gauss-Newton step xi solving H xi = -g (6x6), by least squares where H is singular
    (a direction the points leave unconstrained)."""
    try:
        return np.asarray(np.linalg.solve(H, -g), dtype=np.float64)
    except np.linalg.LinAlgError:
        return np.asarray(np.linalg.lstsq(H, -g, rcond=None)[0], dtype=np.float64)
