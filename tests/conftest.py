"""Shared fixtures: the real data beside the repo, and small synthetic sequences."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def random_pose(rng: np.random.Generator, max_angle_rad: float = 0.2, max_t_m: float = 0.1) -> np.ndarray:
    """A random rigid transform with bounded rotation angle and translation."""
    from server.geometry import exp_se3

    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    xi = np.concatenate([axis * rng.uniform(0, max_angle_rad), rng.uniform(-max_t_m, max_t_m, 3)])
    return exp_se3(xi)


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared data folder {SHARED_DATA} is absent")
    return SHARED_DATA


@pytest.fixture(scope="session")
def demo_clean(tmp_path_factory) -> Path:
    """A small noise-free demo sequence (exact depth), generated once per test session."""
    from server.datasets.demo import DemoSpec, demo_sequence_path

    spec = DemoSpec(frames=24, noise=False)
    return demo_sequence_path(spec, cache_dir=tmp_path_factory.mktemp("demo"), progress=False)
