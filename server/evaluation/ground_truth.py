"""Checks of a ground truth against independent estimates: stretches where the ground truth moves
in a way that every estimate, agreeing among themselves, does not (a glitch of whatever made the
ground truth, e.g. KinectFusion's tracking behind 7-Scenes), and what those stretches cost a
trajectory that follows the images perfectly.

Poses are T_world_camera (N, 4, 4) in metres, one per frame, all trajectories on the same frames.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from server.geometry import invert, orthonormalize, rotation_angle_deg
from server.geometry.arrays import FloatArray


@dataclass(frozen=True)
class Disputed:
    """Frames ``first`` to ``last`` (the motion between them) where the ground truth and every
    estimate part: over some span inside, the truth's relative motion is more than the threshold
    from each estimate's, while the estimates agree with one another."""

    first: int
    last: int
    truth_m: float  # the truth's translation from first to last, metres
    truth_deg: float
    disagreement_m: float  # the smallest over the estimates, of translation of truth^-1 estimate
    disagreement_deg: float  # the rotation of that estimate's difference
    agreement_m: float  # the difference between the two estimates that agree best (0 with one)


def _relative(poses: FloatArray, a: int, b: int) -> FloatArray:
    return invert(poses[a]) @ poses[b]


def _translation(T: FloatArray) -> float:
    return float(np.linalg.norm(T[:3, 3]))


def disputed_stretches(
    truth: FloatArray,
    estimates: list[FloatArray],
    threshold_m: float,
    agree_m: float,
    spans: tuple[int, ...] = (1, 2, 4, 8),
) -> list[Disputed]:
    """Stretches of frames where the ground truth is disputed by every estimate.

    For each span s and frame i, the motion from i to i + s is compared: disputed when the
    truth's differs from every estimate's by more than ``threshold_m`` (translation of the
    difference) and at least two estimates agree with each other within ``agree_m`` (with one
    estimate, the first test alone): two independent methods that agree with each other and not
    with the truth. The steps of overlapping disputed spans join into one stretch, which is then
    trimmed at both ends of the steps that add next to nothing to the disagreement: a one-frame
    jump is one step, not the 8-frame spans around it. A longer span finds a glitch spread over
    several frames that no one step shows.
    """
    if not estimates:
        raise ValueError("need at least one estimate to check the ground truth against")
    if any(e.shape != truth.shape for e in estimates):
        raise ValueError("every trajectory needs the same frames as the ground truth")
    n = len(truth)
    flagged = np.zeros(max(n - 1, 0), dtype=bool)  # step i: frame i to i + 1
    for s in spans:
        for i in range(n - s):
            if _disputed(truth, estimates, i, i + s, threshold_m, agree_m):
                flagged[i : i + s] = True
    out = []
    i = 0
    while i < len(flagged):
        if not flagged[i]:
            i += 1
            continue
        j = i
        while j + 1 < len(flagged) and flagged[j + 1]:
            j += 1
        first, last = _trim(truth, estimates, i, j + 1, threshold_m)
        rel_truth = _relative(truth, first, last)
        diffs = [invert(rel_truth) @ _relative(e, first, last) for e in estimates]
        k = int(np.argmin([_translation(d) for d in diffs]))
        out.append(
            Disputed(
                first,
                last,
                _translation(rel_truth),
                rotation_angle_deg(rel_truth),
                _translation(diffs[k]),
                rotation_angle_deg(diffs[k]),
                _agreement(estimates, first, last),
            )
        )
        i = j + 1
    return out


def _nearest(truth: FloatArray, estimates: list[FloatArray], a: int, b: int) -> float:
    """How far the estimate nearest to the truth is from it over frames a to b, metres."""
    rel_truth_inv = invert(_relative(truth, a, b))
    return min(_translation(rel_truth_inv @ _relative(e, a, b)) for e in estimates)


def _trim(
    truth: FloatArray, estimates: list[FloatArray], first: int, last: int, threshold_m: float
) -> tuple[int, int]:
    """Drop end steps that add less than a tenth of ``threshold_m`` to the disagreement (the
    ground truth's frame-to-frame jitter), keeping those that carry it."""
    tolerance = 0.1 * threshold_m
    while last - first > 1:
        whole = _nearest(truth, estimates, first, last)
        if _nearest(truth, estimates, first + 1, last) >= whole - tolerance:
            first += 1
        elif _nearest(truth, estimates, first, last - 1) >= whole - tolerance:
            last -= 1
        else:
            break
    return first, last


def _agreement(estimates: list[FloatArray], a: int, b: int) -> float:
    rel = [_relative(e, a, b) for e in estimates]
    return min(
        (_translation(invert(p) @ q) for i, p in enumerate(rel) for q in rel[i + 1 :]),
        default=0.0,
    )


def _disputed(
    truth: FloatArray,
    estimates: list[FloatArray],
    a: int,
    b: int,
    threshold_m: float,
    agree_m: float,
) -> bool:
    if _nearest(truth, estimates, a, b) <= threshold_m:
        return False
    return _agreement(estimates, a, b) < agree_m


def with_stretches_replaced(
    truth: FloatArray, estimate: FloatArray, stretches: list[Disputed]
) -> FloatArray:
    """The ground truth with its frame-to-frame motions inside each stretch replaced by the
    estimate's; every other motion stays the truth's. Scored against the truth, it is a
    trajectory that is perfect but for not making the disputed moves: what they cost any method
    that follows the images."""
    replaced = np.zeros(max(len(truth) - 1, 0), dtype=bool)
    for d in stretches:
        replaced[d.first : d.last] = True
    # Composed step by step from the first pose (orthonormalised as it goes): moving every
    # later pose by each replaced step's correction instead amplifies rounding threefold a step.
    out = truth.copy()
    for i, from_estimate in enumerate(replaced):
        step = _relative(estimate if from_estimate else truth, i, i + 1)
        out[i + 1] = orthonormalize(out[i] @ step)
    return out
