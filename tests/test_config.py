import pytest

from server.config import RegistrationConfig
from server.errors import ConfigError
from server.geometry import Intrinsics


def test_overrides_change_one_field_and_keep_the_rest():
    cfg = RegistrationConfig().with_overrides(solver={"dense": False})
    assert cfg.solver.dense is False
    assert cfg.solver.max_iterations == RegistrationConfig().solver.max_iterations


@pytest.mark.parametrize("sections", [{"nosuch": {}}, {"solver": {"nosuch": 1}}])
def test_unknown_settings_are_refused(sections):
    with pytest.raises(ConfigError):
        RegistrationConfig().with_overrides(**sections)


def test_inconsistent_thresholds_are_refused():
    with pytest.raises(ConfigError):
        RegistrationConfig().with_overrides(state={"lost_inliers": 100, "ok_inliers": 50})


@pytest.mark.parametrize("fx", [0.0, -1.0, float("nan")])
def test_absurd_intrinsics_are_refused(fx):
    with pytest.raises(ConfigError):
        Intrinsics(fx, 500.0, 320.0, 240.0, 640, 480)
