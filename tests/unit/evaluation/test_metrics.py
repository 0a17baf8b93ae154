"""ATE / RPE against evo's implementation, Umeyama alignment, and the TUM trajectory format."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from server.errors import TrajectoryError
from server.evaluation.metrics import (
    align_umeyama,
    associate_trajectories,
    ate,
    evaluate,
    format_table,
    rpe,
)
from server.evaluation.trajectory import Trajectory, read_tum, write_tum
from server.geometry import exp_se3
from tests.conftest import missing


@pytest.fixture(scope="module")
def evo() -> SimpleNamespace:
    """evo's metrics and trajectory modules, the reference the comparisons below check against.
    Only those need it: without evo they are skipped here, and fail in CI."""
    try:
        from evo.core import metrics, trajectory
    except ImportError:
        missing("evo is not installed (dev extras: pip install -e '.[dev]')")
    return SimpleNamespace(metrics=metrics, trajectory=trajectory)


def random_pose(
    rng: np.random.Generator, rot_rad: float = np.pi, trans_m: float = 2.0
) -> np.ndarray:
    """A random SE(3) transform: rotation up to ``rot_rad``, translation up to ``trans_m``."""
    axis = rng.normal(size=3)
    omega = axis / np.linalg.norm(axis) * rng.uniform(0, rot_rad)
    return exp_se3(np.concatenate([omega, rng.uniform(-trans_m, trans_m, 3)]))


def fake_trajectory(n: int = 120, rate_hz: float = 30.0, seed: int = 0) -> Trajectory:
    """A hand-held-like random walk: small random motions (~2 deg, ~2 cm) chained from a random
    start pose, stamped at ``rate_hz``."""
    rng = np.random.default_rng(seed)
    poses = [random_pose(rng)]
    for _ in range(n - 1):
        xi = np.concatenate([rng.normal(0, 0.02, 3), rng.normal(0, 0.02, 3)])
        poses.append(poses[-1] @ exp_se3(xi))
    return Trajectory(timestamps=100.0 + np.arange(n) / rate_hz, poses=np.stack(poses))


def noisy_copy(traj: Trajectory, seed: int = 1, sigma: float = 0.01) -> Trajectory:
    """``traj`` with per-pose noise (sigma rad / m), moved by a random rigid transform."""
    rng = np.random.default_rng(seed)
    T = random_pose(rng)
    noise = [exp_se3(rng.normal(0, sigma, 6)) for _ in range(len(traj))]
    poses = np.stack([T @ P @ N for P, N in zip(traj.poses, noise, strict=True)])
    return Trajectory(traj.timestamps.copy(), poses)


def to_evo(evo: SimpleNamespace, traj: Trajectory):
    return evo.trajectory.PoseTrajectory3D(
        poses_se3=list(traj.poses), timestamps=traj.timestamps.copy()
    )


def test_ate_of_rigidly_moved_copy_is_zero():
    gt = fake_trajectory()
    T = random_pose(np.random.default_rng(7))
    est = Trajectory(gt.timestamps, T @ gt.poses)
    result = ate(gt, est)
    assert result["rmse"] < 1e-9
    assert result["max"] < 1e-9
    assert ate(gt, est, align=False)["rmse"] > 0.1


def test_umeyama_recovers_known_transform():
    rng = np.random.default_rng(3)
    src = rng.uniform(-1, 1, (50, 3))
    T = random_pose(rng)
    dst = src @ T[:3, :3].T + T[:3, 3]
    np.testing.assert_allclose(align_umeyama(src, dst), T, atol=1e-10)
    S = align_umeyama(src, 2.5 * dst, with_scale=True)
    np.testing.assert_allclose(np.cbrt(np.linalg.det(S[:3, :3])), 2.5, rtol=1e-10)


def test_umeyama_rejects_degenerate_points():
    with pytest.raises(TrajectoryError, match="degenerate"):
        align_umeyama(np.ones((5, 3)), np.ones((5, 3)))


def test_ate_agrees_with_evo(evo):
    gt = fake_trajectory()
    est = noisy_copy(gt)
    ours = ate(gt, est)
    ref, est_evo = to_evo(evo, gt), to_evo(evo, est)
    est_evo.align(ref)
    ape = evo.metrics.APE(evo.metrics.PoseRelation.translation_part)
    ape.process_data((ref, est_evo))
    stats = ape.get_all_statistics()
    for key in ("rmse", "mean", "median", "max"):
        assert ours[key] == pytest.approx(stats[key], rel=1e-6)


def test_sim3_ate_agrees_with_evo_correct_scale(evo):
    """``ate(align="sim3")`` is evo's ``align(correct_scale=True)``, on an estimate at 0.8 scale."""
    gt = fake_trajectory()
    est = noisy_copy(gt)
    est.poses[:, :3, 3] *= 0.8
    ours = ate(gt, est, "sim3")
    ref, est_evo = to_evo(evo, gt), to_evo(evo, est)
    est_evo.align(ref, correct_scale=True)
    ape = evo.metrics.APE(evo.metrics.PoseRelation.translation_part)
    ape.process_data((ref, est_evo))
    assert ours["rmse"] == pytest.approx(ape.get_all_statistics()["rmse"], rel=1e-6)
    assert ours["rmse"] < ate(gt, est, "se3")["rmse"]


@pytest.mark.parametrize(
    ("delta", "unit", "evo_frames"), [(1, "frames", 1), (5, "frames", 5), (1.0, "seconds", 30)]
)
def test_rpe_agrees_with_evo(evo, delta, unit, evo_frames):
    gt = fake_trajectory()  # 30 Hz: one second is 30 frames
    est = noisy_copy(gt)
    ours = rpe(gt, est, delta, unit)
    for relation, key in (("translation_part", "trans_rmse"), ("rotation_angle_deg", "rot_rmse")):
        metric = evo.metrics.RPE(
            evo.metrics.PoseRelation[relation],
            delta=evo_frames,
            delta_unit=evo.metrics.Unit.frames,
            all_pairs=True,
        )
        metric.process_data((to_evo(evo, gt), to_evo(evo, est)))
        expected = metric.get_statistic(evo.metrics.StatisticsType.rmse)
        assert ours[key] == pytest.approx(expected, rel=1e-6)
    assert ours["pairs"] == len(gt) - evo_frames


def test_rpe_seconds_pairs_each_pose_with_first_pose_at_least_delta_later():
    stamps = np.array([0.0, 0.4, 0.9, 1.0, 1.6, 2.5])
    gt = Trajectory(stamps, fake_trajectory(len(stamps)).poses)
    # pairs: 0->3 (1.0 s), 1->4 (1.2 s), 2->5 (1.6 s), 3->5 (1.5 s); pose 4 has none.
    assert rpe(gt, gt, 1.0, "seconds")["pairs"] == 4
    with pytest.raises(TrajectoryError, match="no pose pairs"):
        rpe(gt, gt, 10.0, "seconds")


def test_evaluate_associates_and_reports_all_metrics():
    gt = fake_trajectory()
    est = noisy_copy(gt)
    est = Trajectory(est.timestamps[::2] + 0.005, est.poses[::2])  # every other frame, late
    result = evaluate(gt, est)
    assert result["matched"] == len(est)
    assert 0 < result["ate_rmse_m"] < 0.05
    assert all(np.isfinite(v) for v in result.values())
    table = format_table({"noisy": result})
    assert table.row_count == 1
    assert len(table.columns) == 7


def test_no_matches_due_to_offset():
    gt = fake_trajectory(20)
    est = Trajectory(gt.timestamps + 1.0, gt.poses)
    with pytest.raises(TrajectoryError, match="max_diff=0.02"):
        associate_trajectories(gt, est, max_diff=0.02)


def test_tum_file_round_trip(tmp_path):
    traj = fake_trajectory(30)
    path = tmp_path / "out" / "poses.txt"
    write_tum(path, traj)
    back = read_tum(path)
    np.testing.assert_allclose(back.timestamps, traj.timestamps, atol=1e-6)
    np.testing.assert_allclose(back.poses, traj.poses, atol=1e-8)
    rows = [line.split() for line in path.read_text().splitlines() if not line.startswith("#")]
    assert all(len(row) == 8 and float(row[7]) >= 0 for row in rows)
    assert list(path.parent.iterdir()) == [path]  # no temp file left behind


@pytest.mark.parametrize(
    "bad_row", ["1.0 0 0 0 0 0 0", "1.0 0 0 zero 0 0 0 1", "1.0 0 0 0 0 0 0 0"]
)
def test_malformed_tum_file_names_file_and_line(tmp_path, bad_row):
    path = tmp_path / "bad.txt"
    path.write_text(f"# header\n1.0 0 0 0 0 0 0 1\n{bad_row}\n")
    with pytest.raises(TrajectoryError, match=r"bad\.txt:3"):
        read_tum(path)


def test_missing_or_empty_tum_file_raises(tmp_path):
    with pytest.raises(TrajectoryError, match="cannot read"):
        read_tum(tmp_path / "absent.txt")
    (tmp_path / "empty.txt").write_text("# nothing\n")
    with pytest.raises(TrajectoryError, match="no poses"):
        read_tum(tmp_path / "empty.txt")


def test_rotation_gain_tells_a_tracker_that_turns_too_little_from_noise():
    from server.evaluation.metrics import rotation_gain

    rng = np.random.default_rng(4)
    n = 200
    xi = np.zeros((n, 6))
    xi[:, :3] = rng.normal(0, 0.02, (n, 3))  # omega, rad per frame
    xi[:, 3:] = rng.normal(0, 0.01, (n, 3))  # m per frame
    gt_poses, slow_poses, noisy_poses = [np.eye(4)], [np.eye(4)], [np.eye(4)]
    for k in range(1, n):
        gt_poses.append(gt_poses[-1] @ exp_se3(xi[k]))
        slow = xi[k].copy()
        slow[:3] *= 0.9  # sees 90 % of each rotation
        slow_poses.append(slow_poses[-1] @ exp_se3(slow))
        noisy = xi[k].copy()
        noisy[:3] += rng.normal(0, 0.004, 3)
        noisy_poses.append(noisy_poses[-1] @ exp_se3(noisy))
    t = np.arange(n) / 30.0
    gt = Trajectory(t, np.array(gt_poses))
    same = rotation_gain(gt, gt)
    assert same["est_on_gt"] == pytest.approx(1.0) and same["gt_on_est"] == pytest.approx(1.0)
    slow = rotation_gain(gt, Trajectory(t, np.array(slow_poses)))
    assert slow["est_on_gt"] == pytest.approx(0.9, abs=0.01)
    assert slow["gt_on_est"] == pytest.approx(1 / 0.9, abs=0.015)
    noisy = rotation_gain(gt, Trajectory(t, np.array(noisy_poses)))
    assert noisy["est_on_gt"] == pytest.approx(1.0, abs=0.03) and noisy["gt_on_est"] < 1.0
