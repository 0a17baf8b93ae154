"""Place verification's parts: mutual descriptor matching with the ratio test, and the rigid
RANSAC over 3D-3D pairs."""

from __future__ import annotations

import numpy as np
import pytest

from server.geometry import Intrinsics
from server.geometry.se3 import exp_se3
from server.registration.place import PlaceFeatures
from server.registration.verify import match_descriptors, ransac_rigid

pytestmark = pytest.mark.slow  # unit, not in the fast tier (tests/conftest.py)

K = Intrinsics(fx=100.0, fy=100.0, cx=31.5, cy=23.5, width=64, height=48)


def _features(descriptors: np.ndarray) -> PlaceFeatures:
    n = len(descriptors)
    return PlaceFeatures(
        np.zeros((n, 2), np.float32), descriptors, np.zeros((n, 3)), np.zeros((6, 8), np.float32), K
    )


def _hamming(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(len(a), len(b)) Hamming distances of 256-bit descriptors."""
    return np.unpackbits(a[:, None, :] ^ b[None, :, :], axis=2).sum(axis=2)


def test_descriptor_matches_are_the_mutual_nearest_neighbours_that_pass_the_ratio_test():
    rng = np.random.default_rng(4)
    a = rng.integers(0, 256, (300, 32), dtype=np.uint8)
    # b: noisy copies of 200 of a's descriptors (a few bits flipped) and 150 unrelated ones.
    flips = np.packbits(rng.random((200, 256)) < 0.08, axis=1)
    b = np.concatenate([a[:200] ^ flips, rng.integers(0, 256, (150, 32), dtype=np.uint8)])
    b = b[rng.permutation(len(b))]
    ratio = 0.9
    pairs = match_descriptors(_features(a), _features(b), ratio)

    d = _hamming(a, b)
    nearest_b = d.argmin(axis=1)
    two = np.sort(d, axis=1)[:, :2]
    nearest_a = d.argmin(axis=0)
    expected = {
        (i, int(nearest_b[i]))
        for i in range(len(a))
        if two[i, 0] < ratio * two[i, 1] and nearest_a[nearest_b[i]] == i
    }
    assert {tuple(map(int, p)) for p in pairs} == expected
    assert 150 < len(expected) <= 200  # most noisy copies found, nothing unrelated
    assert len(match_descriptors(_features(a[:1]), _features(b), ratio)) == 0


def test_ransac_recovers_the_motion_of_most_pairs_and_flags_the_rest():
    rng = np.random.default_rng(5)
    T = exp_se3(np.array([0.2, -0.1, 0.3, 0.1, 0.3, -0.2]))
    Q = rng.uniform(-1.0, 1.0, (120, 3)) + [0.0, 0.0, 2.0]
    P = Q @ T[:3, :3].T + T[:3, 3] + rng.normal(0.0, 0.002, Q.shape)
    wrong = rng.choice(len(P), 40, replace=False)
    P[wrong] += rng.uniform(0.2, 0.5, (40, 3)) * rng.choice([-1, 1], (40, 3))
    found, inliers = ransac_rigid(P, Q, iterations=300, threshold_m=0.02)
    assert np.allclose(found, T, atol=5e-3)
    assert not inliers[wrong].any()
    assert inliers.sum() == len(P) - len(wrong)
    # Three pairs are the least it can fit; fewer give no motion and no inliers.
    _, none = ransac_rigid(P[:2], Q[:2], iterations=10, threshold_m=0.02)
    assert not none.any()
