"""server/evaluation/ground_truth.py: finding where a ground truth moves as no estimate does, and
what such a stretch costs a trajectory that follows the images."""

from __future__ import annotations

import numpy as np
import pytest

from server.evaluation.ground_truth import disputed_stretches, with_stretches_replaced
from server.evaluation.metrics import ate
from server.evaluation.trajectory import Trajectory
from server.geometry import exp_se3, invert

pytestmark = pytest.mark.slow  # unit, not in the fast tier (tests/conftest.py)


def _walk(n: int, seed: int) -> np.ndarray:
    """A smooth hand-held walk: 8 mm and about 0.5 degrees a frame, poses (n, 4, 4)."""
    rng = np.random.default_rng(seed)
    poses = [np.eye(4)]
    for _ in range(n - 1):
        xi = np.r_[rng.normal(0, 0.005, 3), np.array([0.008, 0.0, 0.0]) + rng.normal(0, 0.001, 3)]
        poses.append(poses[-1] @ exp_se3(xi))
    return np.stack(poses)


def _noisy(poses: np.ndarray, sigma_m: float, seed: int) -> np.ndarray:
    """The same motion with a little independent error on every step (an estimate)."""
    rng = np.random.default_rng(seed)
    out = [poses[0]]
    for i in range(len(poses) - 1):
        step = invert(poses[i]) @ poses[i + 1]
        out.append(out[-1] @ step @ exp_se3(np.r_[np.zeros(3), rng.normal(0, sigma_m, 3)]))
    return np.stack(out)


def _with_jump(poses: np.ndarray, at: int, jump_m: np.ndarray) -> np.ndarray:
    """The walk with an extra translation (in the camera frame) on the step at -> at + 1."""
    out = poses.copy()
    C = out[at + 1] @ exp_se3(np.r_[np.zeros(3), jump_m]) @ invert(out[at + 1])
    out[at + 1 :] = np.einsum("ij,njk->nik", C, out[at + 1 :])
    return out


def test_a_jump_only_the_truth_makes_is_found_and_its_cost_measured():
    walk = _walk(120, seed=1)
    truth = _with_jump(walk, 60, np.array([0.0, 0.01, 0.035]))  # 3.6 cm in one frame
    a, b = _noisy(walk, 0.0005, seed=2), _noisy(walk, 0.0005, seed=3)

    found = disputed_stretches(truth, [a, b], threshold_m=0.02, agree_m=0.01)

    assert len(found) == 1
    s = found[0]
    assert s.first <= 60 < s.last and s.last - s.first <= 8
    assert s.disagreement_m == pytest.approx(0.0364, abs=0.004)
    assert s.agreement_m < 0.005
    # Cleared of the jump, the truth is the walk again (up to the estimate's own steps inside the
    # stretch), so the estimates fit it better than they fit the truth.
    stamps = np.arange(len(walk)) / 30.0
    cleared = with_stretches_replaced(truth, a, found)
    gt, gt_cleared = Trajectory(stamps, truth), Trajectory(stamps, cleared)
    floor = ate(gt, gt_cleared)["rmse"]
    # A 3.6 cm step halfway: the rigid alignment splits it and tilts the halves (about 0.9 cm).
    assert 0.005 < floor < 0.02
    assert (
        ate(gt_cleared, Trajectory(stamps, a))["rmse"]
        < 0.3 * ate(gt, Trajectory(stamps, a))["rmse"]
    )


def test_a_truth_the_estimates_follow_is_not_disputed():
    walk = _walk(80, seed=4)
    estimates = [_noisy(walk, 0.0005, seed=5), _noisy(walk, 0.0005, seed=6)]
    assert disputed_stretches(walk, estimates, threshold_m=0.02, agree_m=0.01) == []
    # Replacing nothing gives the truth back.
    assert np.allclose(with_stretches_replaced(walk, estimates[0], []), walk, atol=1e-12)


def test_estimates_that_disagree_with_each_other_do_not_dispute_the_truth():
    """Two estimates that each go their own way say nothing about the ground truth."""
    walk = _walk(80, seed=7)
    truth = _with_jump(walk, 40, np.array([0.0, 0.0, 0.03]))
    a = _with_jump(walk, 40, np.array([0.03, 0.0, 0.0]))
    b = _with_jump(walk, 40, np.array([-0.03, 0.0, 0.0]))
    assert disputed_stretches(truth, [a, b], threshold_m=0.02, agree_m=0.01) == []
    # One estimate alone is taken at its word.
    assert len(disputed_stretches(truth, [a], threshold_m=0.02, agree_m=0.01)) == 1


def test_bad_input_is_refused():
    walk = _walk(10, seed=8)
    with pytest.raises(ValueError, match="at least one estimate"):
        disputed_stretches(walk, [], 0.02, 0.01)
    with pytest.raises(ValueError, match="same frames"):
        disputed_stretches(walk, [walk[:5]], 0.02, 0.01)
