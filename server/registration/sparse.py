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
    return _inverse_3x3(cov_P + R @ cov_Q @ R.T)


def _inverse_3x3(M: FloatArray) -> FloatArray:
    """Inverses of (N, 3, 3) matrices by their adjugate: np.linalg.inv calls LAPACK once per
    matrix, several times slower for hundreds of 3x3 covariances (which are well conditioned)."""
    a, b, c = M[:, 0, 0], M[:, 0, 1], M[:, 0, 2]
    d, e, f = M[:, 1, 0], M[:, 1, 1], M[:, 1, 2]
    g, h, i = M[:, 2, 0], M[:, 2, 1], M[:, 2, 2]
    c00, c01, c02 = e * i - f * h, f * g - d * i, d * h - e * g  # cofactors of the first row
    det = a * c00 + b * c01 + c * c02
    adj = np.stack(
        [c00, c * h - b * i, b * f - c * e,
         c01, a * i - c * g, c * d - a * f,
         c02, b * g - a * h, a * e - b * d],
        axis=1,
    ).reshape(-1, 3, 3)  # fmt: skip
    return adj / det[:, None, None]


def mahalanobis(P: FloatArray, Q: FloatArray, W: FloatArray, T: FloatArray) -> FloatArray:
    """Mahalanobis distances (N,) of r = p - T q under information matrices W (N, 3, 3): all
    that robust weights need, without the normal equations."""
    r = P - (Q @ T[:3, :3].T + T[:3, 3])
    squared: FloatArray = np.einsum("ni,nij,nj->n", r, W, r)
    return np.sqrt(np.maximum(squared, 0.0))


def sparse_equations(
    P: FloatArray, Q: FloatArray, W: FloatArray, T: FloatArray, weights: FloatArray
) -> tuple[NormalEquations, FloatArray]:
    """Normal equations of r = p - T q with information matrices W (N, 3, 3) and per-point
    robust ``weights`` (N,); also returns the residuals' Mahalanobis distances (N,)."""
    y = Q @ T[:3, :3].T + T[:3, 3]
    r = P - y
    # d r / d xi for the left perturbation T <- exp(xi) T: [ [y]_x , -I ].
    J = np.zeros((len(y), 3, 6))
    J[:, 0, 1], J[:, 0, 2] = -y[:, 2], y[:, 1]
    J[:, 1, 0], J[:, 1, 2] = y[:, 2], -y[:, 0]
    J[:, 2, 0], J[:, 2, 1] = -y[:, 1], y[:, 0]
    J[:, :, 3:] = -np.eye(3)
    Wr = (W @ r[:, :, None])[:, :, 0]
    mahalanobis = np.sqrt(np.maximum(np.einsum("ni,ni->n", r, Wr), 0.0))
    # Sum over points of J^T w W J as one (3N, 6)^T (3N, 6) product: a multi-operand einsum
    # would loop in numpy's own kernel instead of BLAS.
    WJ = (W @ J) * weights[:, None, None]
    Jf = J.reshape(-1, 6)
    H = Jf.T @ WJ.reshape(-1, 6)
    g = Jf.T @ (Wr * weights[:, None]).reshape(-1)
    return NormalEquations(H, g), mahalanobis


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
    weights = np.ones(n)
    it = 0
    huber_only = max(2, cfg.max_iterations // 3)
    for it in range(1, cfg.max_iterations + 1):
        W = information(cov_P, cov_Q, T[:3, :3])
        weights = robust_weights(mahalanobis(P, Q, W, T), cfg, reject=it > huber_only)
        if not np.any(weights > 0):
            break
        eq, _ = sparse_equations(P, Q, W, T, weights)
        xi = np.linalg.lstsq(eq.H, -eq.g, rcond=None)[0]
        T = orthonormalize(exp_se3(xi) @ T)
        if np.linalg.norm(xi) < cfg.convergence_step and it > huber_only:
            break
    W = information(cov_P, cov_Q, T[:3, :3])
    m = mahalanobis(P, Q, W, T)
    inliers = m <= cfg.outlier_chi
    eq, _ = sparse_equations(P, Q, W, T, robust_weights(m, cfg, reject=True))
    rmse = float(np.sqrt(np.mean(m[inliers] ** 2))) if inliers.any() else np.inf
    depth = float(np.median(P[:, 2])) if n else 1.0
    return SparseSolution(T, inliers, rmse, scaled_condition(eq.H, depth), it, eq)
