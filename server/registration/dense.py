"""Dense refinement: projective point-to-plane ICP against the keyframe's depth (section III-B),
with an optional photometric term (intensity of the current pixels against the keyframe image).

Correspondences come from projecting current points into the keyframe image, not from a nearest
neighbour search; the sparse term rides along, so that geometry which constrains only some
directions (a floor, one wall) cannot slide the pose along the others.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import cast

import cv2
import numpy as np

from server.geometry import Intrinsics, backproject, exp_se3, orthonormalize
from server.geometry.arrays import Float32Array, FloatArray, GreyImage
from server.registration.config import DepthConfig, SolverConfig
from server.registration.preprocess import axial_sigma
from server.registration.sparse import NormalEquations


@dataclass
class DenseModel:
    """A keyframe's surface at half resolution: vertices and normals in its camera frame."""

    vertices: FloatArray  # (h, w, 3) metres, NaN where unknown
    normals: FloatArray  # (h, w, 3) unit, NaN where unknown
    intrinsics: Intrinsics  # of the half-resolution maps
    intensity: Float32Array | None = None  # (h, w) grey, 0-255, slightly blurred
    gradient: Float32Array | None = None  # (h, w, 2) d intensity / d (u, v), per half-res pixel


def build_dense_model(
    depth: Float32Array, K: Intrinsics, grey: GreyImage | None = None, normal_step_px: int = 2
) -> DenseModel:
    """Vertex and normal maps from a depth image (metres) at half resolution.

    Raw depth noise biases point-to-plane ICP, so the depth is first averaged over 2x2 blocks
    and median-filtered, and normals are taken over a baseline of ``normal_step_px`` half-res
    pixels on each side.
    """
    h, w = depth.shape
    valid = (depth > 0).astype(np.float32)
    summed = cv2.resize(depth * valid, (w // 2, h // 2), interpolation=cv2.INTER_AREA)
    count = cv2.resize(valid, (w // 2, h // 2), interpolation=cv2.INTER_AREA)
    small = np.where(count > 0.99, summed / np.maximum(count, 1e-6), 0.0).astype(np.float32)
    smoothed = cv2.medianBlur(small, 5)
    small = np.where((small > 0) & (smoothed > 0), smoothed, small)
    Kh = K.scaled(0.5)
    hh, ww = small.shape
    u, v = np.meshgrid(np.arange(ww), np.arange(hh))
    z = np.where(small > 0, small, np.nan)
    V = np.stack([(u - Kh.cx) * z / Kh.fx, (v - Kh.cy) * z / Kh.fy, z], axis=-1)
    s = normal_step_px
    N = np.full_like(V, np.nan)
    du = V[s:-s, 2 * s :] - V[s:-s, : -2 * s]
    dv = V[2 * s :, s:-s] - V[: -2 * s, s:-s]
    n = np.cross(du, dv)
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    # Across a depth edge the 'normal' is meaningless: require short, similar baselines.
    span = np.maximum(np.linalg.norm(du, axis=-1), np.linalg.norm(dv, axis=-1))
    ok = (norm[..., 0] > 0) & (span < 0.1 * z[s:-s, s:-s] * s)
    n = np.where(ok[..., None], n / np.maximum(norm, 1e-12), np.nan)
    # Orient normals towards the camera.
    flip = np.sum(n * V[s:-s, s:-s], axis=-1) > 0
    n[flip] *= -1
    N[s:-s, s:-s] = n
    intensity: Float32Array | None = None
    gradient: Float32Array | None = None
    if grey is not None:
        # OpenCV keeps float32 through the blur and the CV_32F Sobel; its stubs do not say so.
        intensity = cast(
            Float32Array, cv2.GaussianBlur(cv2.pyrDown(grey).astype(np.float32), (3, 3), 0)
        )
        gradient = np.stack(
            [
                cv2.Sobel(intensity, cv2.CV_32F, 1, 0, ksize=3) / 8.0,
                cv2.Sobel(intensity, cv2.CV_32F, 0, 1, ksize=3) / 8.0,
            ],
            axis=-1,
        )
    return DenseModel(V.astype(np.float64), N.astype(np.float64), Kh, intensity, gradient)


def sample_dense_points(
    depth: Float32Array, K: Intrinsics, stride: int, grey: GreyImage | None = None
) -> tuple[FloatArray, FloatArray | None]:
    """Every ``stride``-th valid pixel of the current depth, back-projected: (N, 3) metres, and
    the (slightly blurred, like the keyframe's) intensity there (N,), when ``grey`` is given."""
    points, uv = backproject(depth, K, stride)
    if grey is None:
        return points, None
    blurred = cv2.GaussianBlur(grey, (5, 5), 0)
    return points, blurred[uv[:, 1].astype(int), uv[:, 0].astype(int)].astype(np.float64)


def _bilinear(image: Float32Array, u: FloatArray, v: FloatArray) -> FloatArray:
    """Image (h, w[, c]) sampled at float pixels; callers keep (u, v) inside [0, w-1) x [0, h-1)."""
    u0, v0 = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
    a, b = u - u0, v - v0
    if image.ndim == 3:
        a, b = a[:, None], b[:, None]
    return (
        (1 - a) * (1 - b) * image[v0, u0]
        + a * (1 - b) * image[v0, u0 + 1]
        + (1 - a) * b * image[v0 + 1, u0]
        + a * b * image[v0 + 1, u0 + 1]
    )


def photometric_equations(
    K: Intrinsics,
    image: Float32Array,
    gradient: Float32Array,
    Q: FloatArray,
    intensity: FloatArray,
    T: FloatArray,
    weight: float,
    sigma: float,
    huber_k: float,
) -> NormalEquations:
    """Normal equations of e = I_keyframe(pi(T q)) - I_current(q) for current points Q (N, 3)
    with intensities (N,), moved by T_keyframe_current into the keyframe ``image`` (h, w) with
    its ``gradient`` (h, w, 2); ``K``: the intrinsics of that image."""
    y = Q @ T[:3, :3].T + T[:3, 3]
    h, w = image.shape
    z = y[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = y[:, 0] * K.fx / z + K.cx
        v = y[:, 1] * K.fy / z + K.cy
    inside = (z > 0) & (u >= 1) & (u < w - 2) & (v >= 1) & (v < h - 2)
    y, u, v, ref = y[inside], u[inside], v[inside], intensity[inside]
    if len(y) == 0:
        return NormalEquations(np.zeros((6, 6)), np.zeros(6))
    e = _bilinear(image, u, v) - ref
    g = _bilinear(gradient, u, v)
    inv_z = 1.0 / y[:, 2]
    # d e / d y = g^T d pi / d y; then d y / d xi = [ -[y]_x , I ].
    de_dy = np.stack(
        [
            g[:, 0] * K.fx * inv_z,
            g[:, 1] * K.fy * inv_z,
            -(g[:, 0] * K.fx * y[:, 0] + g[:, 1] * K.fy * y[:, 1]) * inv_z**2,
        ],
        axis=1,
    )
    J = np.concatenate([np.cross(y, de_dy), de_dy], axis=1)
    m = np.abs(e) / sigma
    wts = weight * np.where(m <= huber_k, 1.0, huber_k / np.maximum(m, 1e-12)) / sigma**2
    return NormalEquations((J * wts[:, None]).T @ J, (J * wts[:, None]).T @ e)


def dense_equations(
    model: DenseModel,
    Q: FloatArray,
    T: FloatArray,
    max_distance: float,
    weight: float,
    depth_cfg: DepthConfig,
    huber_k: float,
) -> tuple[NormalEquations, int]:
    """Point-to-plane normal equations of current points Q (N, 3) moved by T_keyframe_current,
    matched by projection into the keyframe. Returns the equations and the match count."""
    y = Q @ T[:3, :3].T + T[:3, 3]
    K = model.intrinsics
    h, w = model.vertices.shape[:2]
    z = y[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.rint(y[:, 0] * K.fx / z + K.cx)
        v = np.rint(y[:, 1] * K.fy / z + K.cy)
    inside = (z > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    y = y[inside]
    # One flat index and two row gathers: cheaper than indexing the (h, w, 3) maps twice in 2-D.
    pixel = v[inside].astype(np.int64) * w + u[inside].astype(np.int64)
    p = model.vertices.reshape(-1, 3)[pixel]
    n = model.normals.reshape(-1, 3)[pixel]
    d = y - p
    e = np.einsum("ni,ni->n", n, d)
    close = np.isfinite(e) & (np.abs(e) < max_distance)
    close &= np.einsum("ni,ni->n", d, d) < (3 * max_distance) ** 2
    y, n, e = y[close], n[close], e[close]
    if len(e) == 0:
        return NormalEquations(np.zeros((6, 6)), np.zeros(6)), 0
    sigma = axial_sigma(y[:, 2], depth_cfg) * np.sqrt(2.0)  # both surfaces are noisy
    m = np.abs(e) / sigma
    wts = weight * np.where(m <= huber_k, 1.0, huber_k / m) / sigma**2
    # d e / d xi for T <- exp(xi) T: [ y x n , n ] (the cross product written out: np.cross
    # costs more than the rest of this function on a few thousand rows).
    J = np.empty((len(e), 6))
    J[:, 0] = y[:, 1] * n[:, 2] - y[:, 2] * n[:, 1]
    J[:, 1] = y[:, 2] * n[:, 0] - y[:, 0] * n[:, 2]
    J[:, 2] = y[:, 0] * n[:, 1] - y[:, 1] * n[:, 0]
    J[:, 3:] = n
    Jw = J * wts[:, None]
    return NormalEquations(Jw.T @ J, Jw.T @ e), len(e)


def refine_dense(
    T_init: FloatArray,
    model: DenseModel,
    Q: FloatArray,
    sparse_terms: Callable[[FloatArray], NormalEquations],
    cfg: SolverConfig,
    depth_cfg: DepthConfig,
    intensity: FloatArray | None = None,
) -> tuple[FloatArray, int]:
    """Refine T_keyframe_current with point-to-plane terms, the photometric term (when the model
    and ``intensity`` (N,) of the points Q have it) and the sparse term.

    ``sparse_terms(T) -> NormalEquations`` evaluates the sparse cost at a pose.
    Returns the refined pose and the number of dense matches in the last iteration.
    """
    image, gradient = model.intensity, model.gradient
    photometric = cfg.photometric_weight > 0
    T = T_init.copy()
    matches = 0
    for _ in range(cfg.dense_iterations):
        dense_eq, matches = dense_equations(
            model, Q, T, cfg.dense_max_distance_m, cfg.dense_weight, depth_cfg, cfg.huber_k
        )
        eq = dense_eq + sparse_terms(T)
        if photometric and intensity is not None and image is not None and gradient is not None:
            eq = eq + photometric_equations(
                model.intrinsics,
                image,
                gradient,
                Q,
                intensity,
                T,
                cfg.photometric_weight,
                cfg.photometric_sigma,
                cfg.huber_k,
            )
        xi = np.linalg.lstsq(eq.H, -eq.g, rcond=None)[0]
        T = orthonormalize(exp_se3(xi) @ T)
        if np.linalg.norm(xi) < cfg.dense_convergence_step:
            break
    return T, matches
