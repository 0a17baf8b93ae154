"""Registering a frame against one keyframe: follow its corners into the frame (pyramidal LK),
solve T_keyframe_current (sparse Gauss-Newton), judge how far the pose can be trusted, and
refine it on the keyframe's surface (dense)."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from server.geometry import Intrinsics, backproject_pixels, invert, project
from server.geometry.arrays import BoolArray, Float32Array, FloatArray, GreyImage, IndexArray
from server.registration.config import FlowConfig, RegistrationConfig, StateConfig
from server.registration.dense import DenseModel, refine_dense, sample_dense_points
from server.registration.flow import track_points
from server.registration.keyframe import Keyframe
from server.registration.preprocess import sample_stable_depth
from server.registration.results import TrackingState
from server.registration.sparse import (
    NormalEquations,
    SparseSolution,
    information,
    point_information,
    robust_equations,
    solve_sparse,
)


@dataclass
class Tracks:
    """Corners of the current keyframe still followed, and where they were last seen."""

    ids: IndexArray  # indices into the keyframe's corners
    uv: Float32Array  # (N, 2) pixels in ``grey``
    grey: GreyImage  # the frame they were last seen in


@dataclass
class Registration:
    """Corners of ``kf`` found in the current frame and the pose they give.

    ids, uv: keyframe corner indices and their pixels here, for every corner LK followed.
    with_depth: which of them have trusted depth here; ``points`` and ``solution`` cover those.
    """

    kf: Keyframe
    ids: IndexArray
    uv: Float32Array
    with_depth: BoolArray
    points: FloatArray
    solution: SparseSolution
    guess_from_prior: bool = False  # started from the device's pose, not constant velocity

    def surviving(self) -> BoolArray:
        """Corners worth following on: tracked, and not an outlier where depth was available.
        A corner on a depth hole is kept, as the next frame may measure it."""
        keep = ~self.with_depth
        keep[np.flatnonzero(self.with_depth)[self.solution.inliers]] = True
        return keep


def track_keyframe(
    kf: Keyframe,
    grey: GreyImage,
    depth: Float32Array,
    T_world_pred: FloatArray,
    K: Intrinsics,
    cfg: RegistrationConfig,
    tracks: Tracks | None = None,
) -> Registration | None:
    """Track the keyframe's corners into this frame (depth: cleaned, metres) and solve
    T_keyframe_current from the prediction T_world_pred (4x4, metres).

    ``tracks``: the keyframe's corners as last seen, followed on from there (small steps, the
    usual case); None (or none left) tracks them straight from the keyframe image (after a
    loss). None when too few corners are found with depth."""
    T_kf_pred = invert(kf.T_world_keyframe) @ T_world_pred
    if tracks is not None and len(tracks.ids) > 0:
        ids, uv_from, grey_from = tracks.ids, tracks.uv, tracks.grey
    else:
        ids, uv_from, grey_from = np.arange(len(kf.uv)), kf.uv, kf.grey
    if len(ids) < cfg.state.lost_inliers:
        return None
    # Where the prediction puts the corners in this frame: the start of the LK search.
    T_cur_kf = invert(T_kf_pred)
    guess, z = project(kf.points[ids] @ T_cur_kf[:3, :3].T + T_cur_kf[:3, 3], K)
    guess = np.where(np.isfinite(guess) & (z[:, None] > 0), guess, uv_from)
    uv, ok = track_points(grey_from, grey, uv_from, cfg.flow, guess)
    ids, uv = ids[ok], uv[ok]
    if grey_from is not kf.grey and cfg.flow.keyframe_refine_levels >= 0 and len(ids):
        ids, uv = refine_from_keyframe(kf, grey, ids, uv, cfg.flow)
    zc = sample_stable_depth(depth, uv, cfg.depth)
    with_depth = zc > 0
    if with_depth.sum() < cfg.state.lost_inliers:
        return None
    d_ids = ids[with_depth]
    Q = backproject_pixels(uv[with_depth].astype(np.float64), zc[with_depth], K)
    solution = solve_sparse(
        kf.points[d_ids],
        Q,
        kf.covariances[d_ids],
        point_information(Q, K, cfg.depth),
        T_kf_pred,
        cfg.solver,
    )
    return Registration(kf, ids, uv, with_depth, Q, solution)


def refine_from_keyframe(
    kf: Keyframe, grey: GreyImage, ids: IndexArray, uv: Float32Array, f: FlowConfig
) -> tuple[IndexArray, Float32Array]:
    """Re-align chained tracks straight against the keyframe image (flow.keyframe_refine_*):
    LK from the keyframe's corners, starting where the chain put them; a track that moves
    more than ``keyframe_refine_max_px`` or fails the forward-backward check is dropped."""
    cfg = replace(f, pyramid_levels=f.keyframe_refine_levels, fb_pyramid_levels=0)
    uv_kf, ok = track_points(kf.grey, grey, kf.uv[ids], cfg, uv)
    ok &= np.linalg.norm(uv_kf - uv, axis=1) <= f.keyframe_refine_max_px
    return ids[ok], uv_kf[ok]


def judge(solution: SparseSolution, s: StateConfig) -> TrackingState:
    """How far a sparse solution's pose can be trusted (state config)."""
    n = int(solution.inliers.sum())
    if n < s.lost_inliers or solution.condition < s.min_condition or not np.isfinite(solution.rmse):
        return TrackingState.LOST
    if n < s.ok_inliers or solution.rmse > s.ok_rmse:
        return TrackingState.WEAK
    return TrackingState.OK


def quality(solution: SparseSolution) -> tuple[int, float, float]:
    """(inliers, rmse, condition) of a sparse solution, as a TrackResult reports them."""
    return int(solution.inliers.sum()), solution.rmse, solution.condition


def refine_on_surface(
    reg: Registration,
    dense: DenseModel,
    depth: Float32Array,
    grey: GreyImage,
    K: Intrinsics,
    cfg: RegistrationConfig,
) -> FloatArray:
    """Dense refinement of T_keyframe_current, with the sparse inliers kept in the cost."""
    kf, solution = reg.kf, reg.solution
    inl = solution.inliers
    d_ids = reg.ids[reg.with_depth][inl]
    P_in, Q_in = kf.points[d_ids], reg.points[inl]
    cov_Q = point_information(Q_in, K, cfg.depth)
    W = information(kf.covariances[d_ids], cov_Q, solution.T[:3, :3])

    def sparse_terms(T: FloatArray) -> NormalEquations:
        return robust_equations(P_in, Q_in, W, T, cfg.solver, reject=True)[0]

    photometric = cfg.solver.photometric_weight > 0
    points, intensity = sample_dense_points(
        depth, K, cfg.solver.dense_stride, grey if photometric else None
    )
    T, _ = refine_dense(solution.T, dense, points, sparse_terms, cfg.solver, cfg.depth, intensity)
    return T
