"""Trajectory error metrics: ATE and RPE as in the TUM RGB-D benchmark (Sturm et al., 2012).

Pure functions on Trajectory objects (T_world_camera, metres, seconds). ``ate`` and ``rpe`` take
trajectories that are already associated pose by pose; ``evaluate`` associates them first.
"""

from __future__ import annotations

import logging
from enum import Enum

import numpy as np
from rich.table import Table

from server.errors import TrajectoryError
from server.evaluation.trajectory import Trajectory, associate

logger = logging.getLogger(__name__)


class DeltaUnit(str, Enum):
    """What the RPE's ``delta`` counts."""

    frames = "frames"
    seconds = "seconds"


def associate_trajectories(
    gt: Trajectory, est: Trajectory, max_diff: float = 0.02
) -> tuple[Trajectory, Trajectory]:
    """Keep the poses of ``gt`` and ``est`` whose timestamps match one-to-one within ``max_diff``
    seconds; returns (gt_matched, est_matched) of equal length, in gt order."""
    idx_gt, idx_est = associate(gt.timestamps, est.timestamps, max_diff)
    if len(idx_gt) == 0:
        raise TrajectoryError(
            f"no matching timestamps between ground truth ({len(gt)} poses) and estimate "
            f"({len(est)} poses) with max_diff={max_diff} s"
        )
    logger.debug("associated %d of %d estimated poses", len(idx_gt), len(est))
    return (
        Trajectory(gt.timestamps[idx_gt], gt.poses[idx_gt]),
        Trajectory(est.timestamps[idx_est], est.poses[idx_est]),
    )


def align_umeyama(
    src_points: np.ndarray, dst_points: np.ndarray, with_scale: bool = False
) -> np.ndarray:
    """Least-squares transform T (4x4) with dst ~ T @ src (Umeyama, PAMI 1991).

    src_points, dst_points: (N, 3) corresponding points in metres. with_scale: also fit a scale,
    which then multiplies the rotation block (a Sim(3) matrix). Raises TrajectoryError when the
    points are too few or degenerate (all on one point).
    """
    src = np.asarray(src_points, dtype=np.float64)
    dst = np.asarray(dst_points, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3:
        raise TrajectoryError(f"need two (N, 3) point sets, got {src.shape} and {dst.shape}")
    mean_src, mean_dst = src.mean(axis=0), dst.mean(axis=0)
    src_c, dst_c = src - mean_src, dst - mean_dst
    cov = dst_c.T @ src_c / len(src)
    U, d, Vt = np.linalg.svd(cov)
    if np.count_nonzero(d > np.finfo(float).eps) < 2:
        raise TrajectoryError(f"degenerate point sets ({len(src)} points): cannot align")
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0  # a rotation, not a reflection
    R = U @ S @ Vt
    scale = np.trace(np.diag(d) @ S) / np.mean(np.sum(src_c**2, axis=1)) if with_scale else 1.0
    T = np.eye(4)
    T[:3, :3] = scale * R
    T[:3, 3] = mean_dst - scale * R @ mean_src
    return T


def _check_paired(gt: Trajectory, est: Trajectory) -> None:
    if len(gt) != len(est):
        raise TrajectoryError(
            f"trajectories have {len(gt)} and {len(est)} poses; associate them first "
            "(associate_trajectories)"
        )
    if len(gt) < 2:
        raise TrajectoryError(f"need at least 2 poses to compare, got {len(gt)}")


def _stats(errors: np.ndarray) -> dict[str, float]:
    return {
        "rmse": float(np.sqrt(np.mean(errors**2))),
        "mean": float(np.mean(errors)),
        "median": float(np.median(errors)),
        "max": float(np.max(errors)),
    }


ALIGNMENTS = ("se3", "sim3", "none")


def aligned(gt: Trajectory, est: Trajectory, align: str = "se3") -> Trajectory:
    """``est`` moved onto ``gt`` (associated trajectories): ``se3`` a rigid Umeyama fit of the
    positions, ``sim3`` with a scale too (for monocular or mis-scaled depth), ``none`` as it is.
    The poses' rotations turn with the fit; a Sim(3) fit scales their positions."""
    if align not in ALIGNMENTS:
        raise TrajectoryError(f"alignment {align!r} is not one of {', '.join(ALIGNMENTS)}")
    _check_paired(gt, est)
    if align == "none":
        return est
    T = align_umeyama(est.poses[:, :3, 3], gt.poses[:, :3, 3], with_scale=align == "sim3")
    scale = float(np.cbrt(np.linalg.det(T[:3, :3])))
    R = T[:3, :3] / scale
    poses = est.poses.copy()
    poses[:, :3, :3] = R @ est.poses[:, :3, :3]
    poses[:, :3, 3] = est.poses[:, :3, 3] @ T[:3, :3].T + T[:3, 3]
    return Trajectory(est.timestamps.copy(), poses)


def ate(gt: Trajectory, est: Trajectory, align: bool | str = True) -> dict[str, float]:
    """Absolute trajectory error of associated trajectories: statistics (rmse, mean, median, max,
    metres) of the position differences, after aligning ``est`` to ``gt`` (``aligned``: True or
    "se3" rigid, "sim3" with scale, False or "none" not at all)."""
    mode = "se3" if align is True else "none" if align is False else align
    est = aligned(gt, est, mode)
    return _stats(np.linalg.norm(est.poses[:, :3, 3] - gt.poses[:, :3, 3], axis=1))


def _pairs(gt: Trajectory, delta: float, unit: DeltaUnit) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (i, j): j = i + delta frames, or the first pose at least delta seconds later."""
    n = len(gt)
    if unit is DeltaUnit.frames:
        if delta < 1 or delta != int(delta):
            raise TrajectoryError(f"RPE delta in frames must be a positive integer, got {delta}")
        i = np.arange(n - int(delta))
        return i, i + int(delta)
    if delta <= 0:
        raise TrajectoryError(f"RPE delta in seconds must be positive, got {delta}")
    t = gt.timestamps
    if np.any(np.diff(t) <= 0):
        raise TrajectoryError("RPE over seconds needs strictly increasing timestamps")
    # 1 us slack: timestamps written with 6 decimals do not add up exactly.
    j = np.searchsorted(t, t + delta - 1e-6, side="left")
    i = np.arange(n)
    keep = j < n
    return i[keep], j[keep]


def _rotation_angles_deg(R: np.ndarray) -> np.ndarray:
    """Rotation angles (degrees) of (N, 3, 3) rotations; atan2 keeps small angles accurate."""
    sin = 0.5 * np.linalg.norm(
        np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], 1),
        axis=1,
    )
    cos = 0.5 * (np.trace(R, axis1=1, axis2=2) - 1.0)
    return np.degrees(np.arctan2(sin, cos))


def rpe(
    gt: Trajectory, est: Trajectory, delta: float = 1, delta_unit: DeltaUnit | str = "frames"
) -> dict[str, float]:
    """Relative pose error of associated trajectories over ``delta`` frames or seconds.

    For every pose i paired with j (i + delta frames, or the first pose at least delta seconds
    later): E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j), Q ground truth, P estimate. Returns trans_rmse (m)
    and rot_rmse (deg) over all pairs, plus trans_mean, rot_mean and the pair count.
    No alignment is needed: relative motions do not change under a global rigid transform.
    """
    _check_paired(gt, est)
    i, j = _pairs(gt, delta, DeltaUnit(delta_unit))
    if len(i) == 0:
        raise TrajectoryError(
            f"no pose pairs {delta} {DeltaUnit(delta_unit).value} apart in {len(gt)} poses"
        )
    Q_rel = np.linalg.inv(gt.poses[i]) @ gt.poses[j]
    P_rel = np.linalg.inv(est.poses[i]) @ est.poses[j]
    E = np.linalg.inv(Q_rel) @ P_rel
    trans = np.linalg.norm(E[:, :3, 3], axis=1)
    rot = _rotation_angles_deg(E[:, :3, :3])
    return {
        "trans_rmse": float(np.sqrt(np.mean(trans**2))),
        "rot_rmse": float(np.sqrt(np.mean(rot**2))),
        "trans_mean": float(np.mean(trans)),
        "rot_mean": float(np.mean(rot)),
        "pairs": int(len(i)),
    }


def _rotation_vectors(R: np.ndarray) -> np.ndarray:
    """Axis times angle (radians) of (N, 3, 3) rotations, for angles below pi."""
    angles = np.radians(_rotation_angles_deg(R))
    axis = np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], 1)
    norm = np.linalg.norm(axis, axis=1)
    scale = np.divide(angles, norm, out=np.zeros_like(angles), where=norm > 1e-12)
    return axis * scale[:, None]


def rotation_gain(gt: Trajectory, est: Trajectory, delta: int = 5) -> dict[str, float]:
    """How much of the ground truth's rotation the estimate sees, over ``delta`` frames.

    Each pair (i, i + delta) gives the relative rotation vectors of both (each in its own camera
    frame i: no alignment needed). Returns the least-squares slopes of the estimate on the
    ground truth (``est_on_gt``) and of the ground truth on the estimate (``gt_on_est``). Noise
    in either pulls both slopes below 1; a true gain g gives est_on_gt <= g <= 1 / gt_on_est,
    so est_on_gt < 1 < gt_on_est means the estimate turns less than the ground truth."""
    _check_paired(gt, est)
    i, j = _pairs(gt, delta, DeltaUnit.frames)
    if len(i) == 0:
        raise TrajectoryError(f"no pose pairs {delta} frames apart in {len(gt)} poses")
    a = _rotation_vectors((np.linalg.inv(gt.poses[i]) @ gt.poses[j])[:, :3, :3])
    b = _rotation_vectors((np.linalg.inv(est.poses[i]) @ est.poses[j])[:, :3, :3])
    ab = float(np.sum(a * b))
    return {
        "est_on_gt": ab / float(np.sum(a * a)),
        "gt_on_est": ab / float(np.sum(b * b)),
        "pairs": int(len(i)),
    }


def evaluate(
    gt: Trajectory,
    est: Trajectory,
    max_diff: float = 0.02,
    align: str = "se3",
    delta: float = 1.0,
    delta_unit: DeltaUnit | str = DeltaUnit.seconds,
) -> dict[str, float]:
    """Associate ``est`` with ``gt`` and compute the headline metrics (metres, degrees): ATE
    after ``align`` (se3, sim3 or none), RPE per frame, and RPE over ``delta`` ``delta_unit``
    (1 second unless told; its keys keep the ``per_second`` names, ``rpe_delta`` says which).

    The RPE over delta is NaN (with a warning) when the matched poses span less than delta.
    """
    gt_m, est_m = associate_trajectories(gt, est, max_diff)
    _check_paired(gt_m, est_m)
    per_frame = rpe(gt_m, est_m, 1, DeltaUnit.frames)
    try:
        per_delta = rpe(gt_m, est_m, delta, delta_unit)
    except TrajectoryError as exc:
        logger.warning("RPE over %s %s skipped: %s", delta, DeltaUnit(delta_unit).value, exc)
        per_delta = {"trans_rmse": float("nan"), "rot_rmse": float("nan")}
    return {
        "ate_rmse_m": ate(gt_m, est_m, align)["rmse"],
        "rpe_trans_per_frame_m": per_frame["trans_rmse"],
        "rpe_rot_per_frame_deg": per_frame["rot_rmse"],
        "rpe_trans_per_second_m": per_delta["trans_rmse"],
        "rpe_rot_per_second_deg": per_delta["rot_rmse"],
        "matched": len(gt_m),
    }


# (key in evaluate's result, column header, factor to the shown unit)
TABLE_COLUMNS = (
    ("ate_rmse_m", "ATE RMSE [cm]", 100.0),
    ("rpe_trans_per_frame_m", "RPE trans/frame [cm]", 100.0),
    ("rpe_rot_per_frame_deg", "RPE rot/frame [deg]", 1.0),
    ("rpe_trans_per_second_m", "RPE trans/s [cm]", 100.0),
    ("rpe_rot_per_second_deg", "RPE rot/s [deg]", 1.0),
)


def format_table(rows: dict[str, dict], title: str = "Trajectory error") -> Table:
    """A rich table with one row per run name and the metrics of ``evaluate`` in cm and deg."""
    table = Table(title=title)
    table.add_column("run", style="bold")
    for _, header, _ in TABLE_COLUMNS:
        table.add_column(header, justify="right")
    table.add_column("matched", justify="right")
    for name, metrics in rows.items():
        cells = []
        for key, _, factor in TABLE_COLUMNS:
            value = metrics.get(key)
            cells.append(
                "-" if value is None or not np.isfinite(value) else f"{value * factor:.2f}"
            )
        matched = metrics.get("matched")
        cells.append("-" if matched is None else str(matched))
        table.add_row(name, *cells)
    return table
