"""Geometric verification of a place match: descriptor matches, a rigid 3D-3D RANSAC (Kabsch on
three points), then the tracker's own Gauss-Newton with the sensor noise model.

A place is accepted only when enough matches agree on one rigid motion and fit it within their
depth noise: a wrong place seldom gives more than a handful of consistent matches, and this is
what keeps a frame from elsewhere from being relocalised into a room.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np

from server.geometry import Intrinsics, backproject_pixels, project
from server.geometry.arrays import BoolArray, FloatArray, IndexArray
from server.registration.config import DepthConfig, PlaceConfig, SolverConfig
from server.registration.place import KeyframeDatabase, PlaceFeatures
from server.registration.sparse import point_information, solve_sparse


@dataclass
class PlaceMatch:
    """A verified match of a query image to a keyframe.

    T_keyframe_query: 4x4, metres (maps query camera points into the keyframe's camera frame).
    """

    keyframe_id: int
    T_keyframe_query: FloatArray
    inliers: int  # Gauss-Newton inliers (Mahalanobis)
    rmse: float  # their Mahalanobis RMSE
    matches: int  # descriptor matches tried
    agreement: float  # share of overlapping depth on the keyframe's surface
    overlap: float  # share of the query's depth that lands on the keyframe's
    votes: int = 0  # the database's votes for this keyframe


def match_descriptors(a: PlaceFeatures, b: PlaceFeatures, ratio: float) -> IndexArray:
    """(M, 2) index pairs (into a, into b) that pass the ratio test both ways."""
    if len(a) < 2 or len(b) < 2:
        return np.zeros((0, 2), np.intp)
    matcher = cv2.BFMatcher.create(cv2.NORM_HAMMING)
    ab = matcher.knnMatch(a.descriptors, b.descriptors, k=2)
    pairs = np.array(
        [
            (p[0].queryIdx, p[0].trainIdx)
            for p in ab
            if len(p) == 2 and p[0].distance < ratio * p[1].distance
        ],
        np.intp,
    ).reshape(-1, 2)
    if len(pairs) == 0:
        return pairs
    # The way back only for the descriptors of b that passed (a few hundred of thousands): the
    # same nearest neighbours as matching all of b, at a fraction of the cost.
    of_b = np.unique(pairs[:, 1])
    back = np.full(len(b), -1, np.intp)
    back[of_b] = [m.trainIdx for m in matcher.match(b.descriptors[of_b], a.descriptors)]
    mutual: IndexArray = pairs[back[pairs[:, 1]] == pairs[:, 0]]
    return mutual


def kabsch(P: FloatArray, Q: FloatArray) -> FloatArray:
    """The rigid T (4x4) minimising sum |p - T q|^2 over (N, 3) point pairs, N >= 3."""
    mp, mq = P.mean(axis=0), Q.mean(axis=0)
    U, _, Vt = np.linalg.svd((Q - mq).T @ (P - mp))
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, mp - R @ mq
    return T


def ransac_rigid(
    P: FloatArray, Q: FloatArray, iterations: int, threshold_m: float, seed: int = 0
) -> tuple[FloatArray, BoolArray]:
    """Rigid T with P ~ T Q supported by most pairs (3D distance <= ``threshold_m``): minimal
    samples of three, the best refitted on its inliers. Returns (T 4x4, inliers (N,))."""
    n = len(P)
    if n < 3:
        return np.eye(4), np.zeros(n, bool)
    rng = np.random.default_rng(seed)
    # Three distinct indices per sample, drawn at once: i < n, j < n - 1 and k < n - 2, each
    # moved past the ones drawn before it.
    i = rng.integers(0, n, iterations)
    j = rng.integers(0, n - 1, iterations)
    j += j >= i
    k = rng.integers(0, n - 2, iterations)
    lo, hi = np.minimum(i, j), np.maximum(i, j)
    k += k >= lo
    k += k >= hi
    samples = np.stack([i, j, k], axis=1)
    # Every hypothesis at once: a batched Kabsch over the minimal samples.
    Ps, Qs = P[samples], Q[samples]  # (I, 3, 3): sample, point, axis
    mp, mq = Ps.mean(axis=1, keepdims=True), Qs.mean(axis=1, keepdims=True)
    U, _, Vt = np.linalg.svd(np.swapaxes(Qs - mq, 1, 2) @ (Ps - mp))
    V, Ut = np.swapaxes(Vt, 1, 2), np.swapaxes(U, 1, 2)
    flip = np.ones((len(samples), 3))
    flip[:, 2] = np.sign(np.linalg.det(V @ Ut))
    R = (V * flip[:, None, :]) @ Ut
    t = mp[:, 0] - np.einsum("kij,kj->ki", R, mq[:, 0])
    residual = np.linalg.norm(P[None] - (np.einsum("kij,nj->kni", R, Q) + t[:, None]), axis=2)
    support = residual <= threshold_m
    # A degenerate (nearly collinear) sample fixes no rotation.
    area = np.linalg.norm(np.cross(Qs[:, 1] - Qs[:, 0], Qs[:, 2] - Qs[:, 0]), axis=1)
    support &= (area >= 1e-4)[:, None]
    best = support[int(np.argmax(support.sum(axis=1)))]
    if best.sum() < 3:
        return np.eye(4), best
    T = kabsch(P[best], Q[best])
    inliers = np.linalg.norm(P - (Q @ T[:3, :3].T + T[:3, 3]), axis=1) <= threshold_m
    return (kabsch(P[inliers], Q[inliers]) if inliers.sum() >= 3 else T), inliers


def surface_agreement(
    keyframe: PlaceFeatures, query: PlaceFeatures, T_keyframe_query: FloatArray, cfg: PlaceConfig
) -> tuple[float, float]:
    """(agreement, overlap) of the query's shrunk depth moved into the keyframe by
    ``T_keyframe_query``: overlap, the share of its measured pixels that land on measured
    keyframe depth; agreement, the share of those within max(agree_m, agree_ratio * z) of it."""
    q = query.depth
    v, u = np.nonzero(q > 0)
    if len(u) == 0:
        return 0.0, 0.0
    points = backproject_pixels(
        np.stack([u, v], axis=1).astype(np.float64), q[v, u], query.intrinsics
    )
    moved = points @ T_keyframe_query[:3, :3].T + T_keyframe_query[:3, 3]
    uv, z = project(moved, keyframe.intrinsics)
    h, w = keyframe.depth.shape
    ok = np.isfinite(uv).all(axis=1) & (z > 0)
    ui = np.rint(np.where(ok, uv[:, 0], -1)).astype(np.int64)
    vi = np.rint(np.where(ok, uv[:, 1], -1)).astype(np.int64)
    ok &= (ui >= 0) & (ui < w) & (vi >= 0) & (vi < h)
    z_kf = np.zeros(len(z))
    z_kf[ok] = keyframe.depth[vi[ok], ui[ok]]
    seen = ok & (z_kf > 0)
    if not seen.any():
        return 0.0, 0.0
    tolerance = np.maximum(cfg.agree_m, cfg.agree_ratio * z_kf[seen])
    agree = np.abs(z[seen] - z_kf[seen]) <= tolerance
    return float(agree.mean()), float(seen.mean())


def verify_place(
    keyframe: PlaceFeatures,
    query: PlaceFeatures,
    K: Intrinsics,
    cfg: PlaceConfig,
    solver: SolverConfig,
    depth_cfg: DepthConfig,
    keyframe_id: int = -1,
) -> PlaceMatch | None:
    """T_keyframe_query from descriptor matches, or None when the geometry does not confirm it.

    RANSAC finds the motion most matches agree on; the project's Gauss-Newton (anisotropic depth
    noise, robust weights; :func:`server.registration.sparse.solve_sparse`) refines it over all
    matches. Accepted when it keeps ``cfg.min_inliers`` inliers, ``cfg.min_inlier_ratio`` of the
    matches, with a Mahalanobis RMSE under ``cfg.max_rmse``."""
    pairs = match_descriptors(keyframe, query, cfg.match_ratio)
    if len(pairs) < cfg.min_inliers:
        return None
    P, Q = keyframe.points[pairs[:, 0]], query.points[pairs[:, 1]]
    depth_cfg = replace(depth_cfg, lateral_noise_px=cfg.lateral_noise_px)
    T0, ransac_inliers = ransac_rigid(P, Q, cfg.ransac_iterations, cfg.ransac_threshold_m, cfg.seed)
    if ransac_inliers.sum() < cfg.min_inliers:
        return None
    solution = solve_sparse(
        P, Q, point_information(P, K, depth_cfg), point_information(Q, K, depth_cfg), T0, solver
    )
    n = int(solution.inliers.sum())
    if (
        n < cfg.min_inliers
        or n < cfg.min_inlier_ratio * len(pairs)
        or not solution.rmse <= cfg.max_rmse
    ):
        return None
    agreement, overlap = surface_agreement(keyframe, query, solution.T, cfg)
    if agreement < cfg.min_agreement or overlap < cfg.min_overlap:
        return None
    return PlaceMatch(keyframe_id, solution.T, n, solution.rmse, len(pairs), agreement, overlap)


def find_place(
    database: KeyframeDatabase,
    query: PlaceFeatures,
    K: Intrinsics,
    cfg: PlaceConfig,
    solver: SolverConfig,
    depth_cfg: DepthConfig,
    allowed: set[int] | None = None,
    tried: list[int] | None = None,
) -> PlaceMatch | None:
    """The best verified keyframe for ``query`` among the database's candidates (most inliers),
    or None. ``allowed``: keyframe ids that may match (None: all). ``tried``: when given, the
    candidates' ids are appended to it (verified or not: a caller counts the refused)."""
    best: PlaceMatch | None = None
    for kf_id, votes in database.candidates(query, cfg, allowed):
        if tried is not None:
            tried.append(kf_id)
        found = verify_place(
            database.entry(kf_id).features, query, K, cfg, solver, depth_cfg, kf_id
        )
        if found is not None and (best is None or found.inliers > best.inliers):
            found.votes = votes
            best = found
    return best
