"""Every registration parameter, with its default and units: the ``registration`` section of the
one configuration (server/config.py). Plain frozen dataclasses, so that the tracker needs no
settings machinery; pydantic validates them when the configuration is loaded."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields, replace
from typing import Any

from server.errors import ConfigError


@dataclass(frozen=True)
class FeatureConfig:
    """FAST corners on a scale pyramid (paper, section III-A)."""

    pyramid_levels: int = 3  # levels, each half the size of the previous one
    fast_threshold: int = 12  # intensity difference, 0-255
    max_features: int = 600  # cap over all levels
    grid_cols: int = 16  # buckets spread the corners over the image
    grid_rows: int = 12
    min_distance_px: float = 8.0  # at full resolution; corners closer than this are dropped


@dataclass(frozen=True)
class FlowConfig:
    """Pyramidal Lucas-Kanade tracking with a forward-backward check."""

    # 17 px rather than 21: a third less work per iteration, and a smaller window straddles
    # fewer depth edges (synthetic_room0 ATE 0.39 -> 0.26 cm, 7-Scenes unchanged within noise).
    window_px: int = 17
    pyramid_levels: int = 3  # LK pyramid levels above the full image
    # The backward (checking) pass starts where a correct track must land, so it needs no
    # coarse levels to find it; one level above the full image leaves slack for small errors.
    fb_pyramid_levels: int = 1
    max_iterations: int = 30
    epsilon: float = 0.01  # px, LK convergence
    max_fb_error_px: float = 1.0  # forward-backward round-trip error


@dataclass(frozen=True)
class DepthConfig:
    """Which depths are trusted, and how noisy they are (Kinect-like model)."""

    min_depth_m: float = 0.2
    max_depth_m: float = 6.0
    # A keypoint's depth must be stable over its 3x3 neighbourhood: max - min below this
    # fraction of the depth (rejects depth edges, where colour and depth disagree most).
    max_local_depth_spread: float = 0.03
    # Axial noise sigma(z) = a + b * (z - 0.4)^2 in metres (Nguyen et al., 2012).
    axial_noise_a_m: float = 0.0012
    axial_noise_b_per_m: float = 0.0019
    lateral_noise_px: float = 0.8  # pixel error of a tracked corner


@dataclass(frozen=True)
class SolverConfig:
    """Gauss-Newton on SE(3) with fixed correspondences (eqs. 7-9) and dense refinement."""

    max_iterations: int = 15
    convergence_step: float = 1e-6  # stop when |xi| (rad and m mixed) falls below this
    huber_k: float = 2.0  # Mahalanobis distance where Huber weighting starts
    outlier_chi: float = 4.0  # correspondences beyond this Mahalanobis distance are outliers
    # Dense refinement: projective point-to-plane ICP against the keyframe's smoothed depth.
    dense: bool = True
    dense_stride: int = 8  # sample every n-th pixel of the current depth
    dense_iterations: int = 6
    # Stop refining when |xi| falls below this (rad and m mixed): steps shrink about tenfold per
    # iteration, and one of 3e-5 (0.03 mm at 1 m) is far below the per-frame error.
    dense_convergence_step: float = 3e-5
    dense_max_distance_m: float = 0.05
    dense_weight: float = 0.05  # weight of one dense residual relative to one sparse one
    # Photometric term: intensity of current pixels against the keyframe image (0 = off).
    photometric_weight: float = 0.0
    photometric_sigma: float = 4.0  # intensity noise, grey levels 0-255


@dataclass(frozen=True)
class KeyframeConfig:
    """When to start a new keyframe."""

    min_tracked_ratio: float = 0.5  # of the keyframe's features still tracked
    min_tracked: int = 80
    max_translation_m: float = 0.25
    max_rotation_deg: float = 15.0
    recent_keyframes: int = 8  # kept for relocalisation after a lost frame


@dataclass(frozen=True)
class StateConfig:
    """How a frame is judged ok, weak or lost."""

    ok_inliers: int = 40
    lost_inliers: int = 12
    # Mahalanobis RMSE of the inliers above which the frame is weak; a 3D residual that fits
    # its noise model has an RMSE of sqrt(3) = 1.73.
    ok_rmse: float = 3.0
    min_condition: float = 1e-4  # smallest / largest eigenvalue of the scaled J^T J


@dataclass(frozen=True)
class PriorConfig:
    """The device's own camera pose (e.g. ARCore/ARKit visual-inertial odometry) as a prior.

    Only the prior's motion between frames is trusted (it drifts over long spans): the initial
    guess of a frame is the last tracked pose moved by the prior's motion since that frame. The
    fixed transform between the device's world and the map is estimated from well-tracked frames.
    """

    enabled: bool = True  # use a prior when ``track`` is given one
    # The latest ok frames whose (map pose, prior) pairs estimate T_world_device: few enough to
    # follow a drifting prior, enough that one poorly tracked frame does not move it.
    alignment_frames: int = 15
    # A prior that moved more than this since the last tracked frame is taken as a reset of the
    # device's own tracking, not as motion: the frame falls back to the guess without a prior.
    max_motion_m: float = 1.0
    max_motion_deg: float = 90.0
    # When no keyframe registers a frame, start a new keyframe at the prior's pose rather than
    # stay lost (see Tracker._resume_from_prior).
    resume_after_loss: bool = True


@dataclass(frozen=True)
class RegistrationConfig:
    """All parameters of the registration pipeline."""

    features: FeatureConfig = field(default_factory=FeatureConfig)
    flow: FlowConfig = field(default_factory=FlowConfig)
    depth: DepthConfig = field(default_factory=DepthConfig)
    solver: SolverConfig = field(default_factory=SolverConfig)
    keyframes: KeyframeConfig = field(default_factory=KeyframeConfig)
    state: StateConfig = field(default_factory=StateConfig)
    prior: PriorConfig = field(default_factory=PriorConfig)

    def __post_init__(self) -> None:
        if (
            self.features.pyramid_levels < 1
            or self.flow.pyramid_levels < 0
            or self.flow.fb_pyramid_levels < 0
        ):
            raise ConfigError(
                "registration.features.pyramid_levels must be >= 1, "
                "registration.flow.pyramid_levels and .fb_pyramid_levels >= 0"
            )
        if not 0 < self.depth.min_depth_m < self.depth.max_depth_m:
            raise ConfigError("registration.depth: need 0 < min_depth_m < max_depth_m")
        if self.state.lost_inliers >= self.state.ok_inliers:
            raise ConfigError(
                "registration.state.lost_inliers must be below registration.state.ok_inliers"
            )
        if self.solver.dense_stride < 1:
            raise ConfigError("registration.solver.dense_stride must be >= 1")
        p = self.prior
        if p.alignment_frames < 1 or p.max_motion_m <= 0 or p.max_motion_deg <= 0:
            raise ConfigError(
                "registration.prior: need alignment_frames >= 1, max_motion_m > 0 and "
                "max_motion_deg > 0"
            )

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    def with_overrides(self, **sections: dict[str, Any]) -> RegistrationConfig:
        """A copy with some fields changed, e.g. ``with_overrides(solver={"dense": False})``."""
        names = {f.name for f in fields(self)}
        changed: dict[str, Any] = {}
        for section, values in sections.items():
            if section not in names:
                raise ConfigError(f"unknown config section {section!r}; known: {sorted(names)}")
            try:
                changed[section] = replace(getattr(self, section), **values)
            except TypeError as exc:
                raise ConfigError(f"bad field in section {section!r}: {exc}") from exc
        return replace(self, **changed)
