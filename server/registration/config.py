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
    # Corners followed frame to frame wander (each step adds a little LK error). With this on,
    # each chained track is re-aligned straight against the keyframe's image (LK from the
    # keyframe corner, starting at the chained position, this many pyramid levels above the full
    # image; -1 = off), so its error no longer grows with the keyframe's age.
    keyframe_refine_levels: int = -1
    # A re-aligned track further than this from the chained one is dropped (a wrong match).
    keyframe_refine_max_px: float = 2.0


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
    # Colour focal length over depth focal length, for colour images not registered to depth
    # (raw Kinect): depth pixel c + (uv - c) / scale + offset shows what colour pixel uv does.
    # 1 = registered. Applied where frames come in (calibration.ColourToDepth: colour is
    # resampled onto the depth image), not inside the tracker.
    colour_focal_scale: float = 1.0
    colour_offset_u_px: float = 0.0  # ... plus this offset (depth pixels)
    colour_offset_v_px: float = 0.0
    # Estimate the three above from the first frame (colour edges laid on depth edges,
    # server/registration/calibration.py); kept only when clearly better than the identity, and
    # tried only on full-size depth not registered by the device (not a phone's).
    estimate_colour_registration: bool = True


@dataclass(frozen=True)
class SolverConfig:
    """Gauss-Newton on SE(3) with fixed correspondences (eqs. 7-9) and dense refinement."""

    max_iterations: int = 15
    convergence_step: float = 1e-6  # stop when |xi| (rad and m mixed) falls below this
    huber_k: float = 2.0  # Mahalanobis distance where Huber weighting starts
    outlier_chi: float = 4.0  # correspondences beyond this Mahalanobis distance are outliers
    # Dense refinement: projective point-to-plane ICP against the keyframe's smoothed depth.
    # Off by default since TUM RGB-D's motion-capture truth (independent of any SLAM method)
    # showed it pulling the pose off on real Kinect depth: tum_fr1_xyz tracker-only ATE 3.61 ->
    # 1.61 cm, RPE/s 1.32 -> 0.93 deg, and the same at 2x-4x the motion (every 2nd-4th frame:
    # 2.45-2.84 -> 1.54-2.10 cm); with loop closure (``track``) 1.59 -> 1.35 cm. A depth-only
    # surface fit takes on the structured-light sensor's low-frequency depth distortion, which
    # the sparse term, whose corners fix rotation through their image bearings, barely feels
    # (a translation-only dense step still gave 3.01 cm). It helped where the depth is exact
    # (synthetic_room0 0.16 against 0.20 cm without it, 0.19 with keyframes.window=2) and on
    # 7scenes_a, whose truth is KinectFusion's own dense fit (``track`` 2.51 against 2.80 cm).
    # With it off, a keyframe keeps its cleaned depth and builds its surface only when
    # relocalisation first refines a pose on it (Keyframe.surface).
    dense: bool = False
    dense_stride: int = 8  # sample every n-th pixel of the current depth
    dense_iterations: int = 6
    # Stop refining when |xi| falls below this (rad and m mixed): steps shrink about tenfold per
    # iteration, and one of 3e-5 (0.03 mm at 1 m) is far below the per-frame error.
    dense_convergence_step: float = 3e-5
    dense_max_distance_m: float = 0.05
    # Weight of one dense residual relative to one sparse one. 0.2 rather than 0.05 (with
    # keyframes.window=1): synthetic_room0 ATE 0.185 -> 0.159 cm, 7scenes_a 4.45 -> 4.42 cm,
    # and at stride 2 / 3 0.213 -> 0.19 / 4.51 -> 4.07 cm; 1.0 and above drift on 7scenes_a
    # (5.1-5.3 cm), whose colour is not registered to depth (benchmarks/README.md, "Drift").
    dense_weight: float = 0.2
    # Photometric term: intensity of current pixels against the keyframe image (0 = off).
    photometric_weight: float = 0.0
    photometric_sigma: float = 4.0  # intensity noise, grey levels 0-255


@dataclass(frozen=True)
class KeyframeConfig:
    """When to start a new keyframe."""

    min_tracked_ratio: float = 0.5  # of the keyframe's features still tracked
    min_tracked: int = 80  # at 640x480; less on smaller images (keyframes.min_tracked)
    max_translation_m: float = 0.25
    max_rotation_deg: float = 15.0
    recent_keyframes: int = 8  # kept for relocalisation after a lost frame
    # Which earlier keyframe a due keyframe change tries first: "nearest" (pose distance) or
    # "oldest" (least drift accumulated along the keyframe chain), among those in reach.
    switch_order: str = "nearest"
    # Windowed keyframe refinement: a frame about to become a keyframe is also registered
    # against up to this many other recent keyframes (newest first, within window_reach times
    # max_translation_m and max_rotation_deg), and its pose is solved jointly over all of them,
    # each keyframe's sparse terms weighted by their own information (0 = off: the pose from the
    # current keyframe alone). One keyframe within 3x: synthetic_room0 ATE 0.264 -> 0.204 cm
    # (sparse), 0.243 -> 0.185 cm (sparse + dense); 7scenes_a 3.90 -> 3.82, 4.48 -> 4.45 cm;
    # two keyframes helped the synthetic room more but made 7scenes_a sparse + dense worse
    # (benchmarks/README.md, "Drift"). Two since dense refinement is off (sparse only,
    # 2026-12-04): tum_fr1_xyz 1.61 -> 1.53 cm tracker-only (1.56 -> 1.44 / 2.10 -> 1.97 at
    # every 3rd / 4th frame), synthetic_room0 0.20 -> 0.19 cm; 7scenes_a 2.74 -> 2.80 (track).
    window: int = 2
    # ... and at most this many while the caller is behind (``Tracker.pace``): each costs a
    # registration (~7 ms at 640x288, on every keyframe) that a server dropping frames lacks.
    # benchmarks/registration.py --drop every2 every3 (tum_fr1_xyz, ATE cm, window 2 / 1 / 0):
    # 1.55 / 1.51 / 1.72 and 1.44 / 1.57 / 1.50; p90 ms per frame 37-39 / 28-30 / 23.
    window_when_behind: int = 1
    window_reach: float = 3.0
    # Switching back needs this many of the old keyframe's corners tracked, as a multiple of
    # min_tracked_ratio (and at least min_tracked), and the pose within this share of
    # max_translation_m / max_rotation_deg.
    switch_tracked_factor: float = 1.5
    switch_reach: float = 0.5
    # At most this many earlier keyframes registered per due change: the nearest seldom fails
    # where a farther one holds, and each try is a whole registration. A phone's narrow view
    # (640x288) tried 2.6 per change, all failing, 1.4 ms of every frame (7scenes_a).
    switch_tries: int = 1


@dataclass(frozen=True)
class StateConfig:
    """How a frame is judged ok, weak or lost."""

    ok_inliers: int = 40
    lost_inliers: int = 12
    # Mahalanobis RMSE of the inliers above which the frame is weak; a 3D residual that fits
    # its noise model has an RMSE of sqrt(3) = 1.73.
    ok_rmse: float = 3.0
    min_condition: float = 1e-4  # smallest / largest eigenvalue of the scaled J^T J
    # A frame whose colour or depth image is the very same as the frame before's is out of step:
    # a sensor that delivers depth slower than colour (or a dropped frame filled with a repeat)
    # pairs one moment's colour with another's depth, and corners paired that way give a wrong
    # pose. Such a frame keeps the previous frame's pose (moved by the device's motion when it
    # carries a prior) and state, and is not tracked, fused or made a keyframe
    # (TrackResult.repeated says which image repeated). 7scenes_a has 75 of them in
    # 600 frames: 2.83 -> 2.7 cm (benchmarks/README.md, "Where 7scenes_a's ATE comes from").
    hold_repeated_frames: bool = True


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
class PlaceConfig:
    """Place recognition (ORB descriptors with depth per keyframe) and its geometric check.

    Used to relocalise a frame that has no pose guess (opening a saved room) and to find loops.
    """

    # ORB keypoints detected per image, before the depth check: 2000 rather than 1000 nearly
    # doubles the matches that survive verification on 7scenes_a.
    orb_features: int = 2000
    # Database look-up: every query descriptor votes for the keyframe of its nearest database
    # descriptor when that lies within this Hamming distance (of 256 bits).
    vote_max_hamming: int = 64
    # Descriptors that take part in the vote, evenly picked: of the query, and of each keyframe.
    vote_features: int = 400
    candidates: int = 3  # keyframes with the most votes that are verified geometrically
    min_votes: int = 10  # a keyframe with fewer votes is not verified at all
    # Verification: ratio test between one query and one keyframe's descriptors.
    match_ratio: float = 0.9
    # ORB keypoints (pixel grid, 1.2x pyramid steps) are placed less precisely than the
    # tracker's sub-pixel LK corners: their lateral noise in the verification's noise model.
    lateral_noise_px: float = 2.0
    ransac_iterations: int = 300
    ransac_threshold_m: float = 0.05  # 3D distance of a RANSAC inlier
    # Accepted when the Gauss-Newton refinement (Mahalanobis, registration.solver) keeps at
    # least this many inliers, this share of the RANSAC sample, and this RMSE.
    min_inliers: int = 20
    min_inlier_ratio: float = 0.25
    max_rmse: float = 3.0
    # Surface check: the query's depth (shrunk by depth_shrink, every n-th pixel) moved into the
    # keyframe must lie on the keyframe's depth (within max(agree_m, agree_ratio * z)) for at
    # least min_agreement of the pixels that land on measured keyframe depth, and those must be
    # at least min_overlap of the query's pixels. Descriptors alone accepted wrong places on
    # 7scenes_a (repeated structure, 20-50 cm off, benchmarks/README.md "Rooms").
    depth_shrink: int = 8
    agree_m: float = 0.05
    agree_ratio: float = 0.03
    min_agreement: float = 0.7
    min_overlap: float = 0.2
    seed: int = 0  # RANSAC's random sampling: the same input gives the same answer


@dataclass(frozen=True)
class RelocaliseConfig:
    """Recovery after a loss (server/registration/relocalise.py, Tracker._recover).

    Every keyframe the tracker makes is described for place recognition (ORB with depth, as
    ``place``, but lighter: this runs inside a frame's time); a frame flow cannot register is
    looked up among them in the same frame. When nothing registers ``reinit_after`` frames in a
    row, a new map segment starts from the current frame at the motion model's pose: tracked on
    its own, reported weak and not fused, and merged into the map (moved rigidly) as soon as a
    look-up links one of its frames to the map's keyframes.
    """

    enabled: bool = True
    # ORB keypoints per image and descriptors that vote (of the query and of each keyframe):
    # half and fewer than ``place``'s, so that describing a keyframe costs ~8 ms and a look-up
    # with two verifications ~40-60 ms on a 640x480 frame.
    orb_features: int = 1000
    vote_features: int = 200
    # Keyframes voted on per frame, nearest the last good pose first; a frame that finds none
    # goes on with the next ones, so that the whole map is searched over a few frames.
    vote_keyframes: int = 60
    # Keyframes verified per frame, the current one included: each verification costs 15-25 ms
    # on 640x480 (descriptor matching, RANSAC, Gauss-Newton), so two keep a look-up within a
    # 15 fps frame's time; RANSAC samples per verification likewise fewer than ``place``'s (at
    # 40 % inliers, 150 samples still miss a motion once in 10^4).
    candidates: int = 2
    ransac_iterations: int = 150
    reinit_after: int = 3  # frames lost in a row before a new segment starts
    # In a segment, every n-th frame is looked up in the map (a look-up costs as much as
    # tracking a frame).
    merge_every: int = 2
    # ... and every n-th while the server is behind (it dropped a frame for a newer one within
    # the last second): a look-up that fails costs ~50 ms at 640x288 against ~8 for tracking,
    # and on a busy machine looking up every other frame dropped more frames still.
    merge_every_behind: int = 8
    # Keyframes older than the recent ones kept (image and corners, ~0.4 MB each at 640x480)
    # so that a place found among them is refined by flow; the oldest go first. The place
    # database itself keeps every keyframe.
    archive_keyframes: int = 150
    # A segment's keyframes (images and segment poses, ~2 MB each at 640x480) kept by whoever
    # fuses (the live session, ``track``) to go into the map at their corrected poses once the
    # segment merges; the oldest beyond this are left out.
    segment_keyframes_kept: int = 30
    # A place that flow cannot follow (too wide a baseline) is refined by ICP against the
    # keyframe's surface; it stands when this share of the frame's points find that surface.
    min_icp_overlap: float = 0.5


@dataclass(frozen=True)
class LoopConfig:
    """Loop closure over keyframes (server/registration/loops.py). ``enabled``: offline, in
    ``track`` (keyframes looked up behind tracking, the graph optimised at the end), on by default:
    on 7scenes_a it costs ``track`` 1-3 s of its 23-25 s and takes the ATE from 2.71 to 2.51 cm
    (benchmarks/README.md, "Loop closure"). ``live``: in the background of every live session that
    keeps its room's keyframes (``server.save_rooms``) and starts an empty world (a session
    continuing in a saved room has none: server/sessions/runtime/loop_closing.py says why); off by
    default: on 2 cores it costs each phone's session 14-36 ms more server CPU per frame (a third of
    it re-fusing the map, a seventh the look-ups), and two phones at 15 fps then miss capacity's
    target (10 % of frames without a pose against 3 % with it off; ``benchmarks/live_loops.py``,
    benchmarks/README.md, "Online, in live sessions")."""

    enabled: bool = True
    live: bool = False
    min_separation: int = 10  # a loop joins keyframes at least this many keyframes apart
    icp_distance_m: float = 0.05  # point-to-plane refinement of a loop; the graph's too
    min_icp_fitness: float = 0.5  # share of the new keyframe's depth that must fit the old one
    # Every n-th depth pixel in the keyframes' clouds (ICP of a loop, every edge's information):
    # 8 rather than 4 gives a quarter of the points, ICP and information matrices about a third
    # of the CPU, the same loops on 7scenes_a and ATEs within +-0.04 cm (benchmarks/README.md,
    # "Loop closure").
    cloud_stride: int = 8
    preference: float = 1.0  # Open3D's preference_loop_closure (0.1 odometry-heavy, 2 loops)
    # A loop edge's information matrix (Open3D's, from the two keyframes' depth) times this.
    # Loops join keyframes seen from other places and are less accurate than their point count
    # says (7scenes_a played once: 2.46 cm median against 0.71 cm for odometry edges). At 1.0
    # the correction made 7scenes_a worse (2.83 -> 3.49 cm); at 0.01 it makes every case better:
    # 7scenes_a 2.83 -> 2.63, there and back 200 / 300 1.87 -> 1.86 / 2.19 -> 2.02 cm,
    # synthetic_room0 0.188 -> 0.153 / 0.231 -> 0.181 cm (benchmarks/README.md, "Loop closure").
    loop_information_scale: float = 0.01


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
    place: PlaceConfig = field(default_factory=PlaceConfig)
    relocalise: RelocaliseConfig = field(default_factory=RelocaliseConfig)
    loops: LoopConfig = field(default_factory=LoopConfig)

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

        q = self.place
        if q.orb_features < 10 or q.candidates < 1 or q.min_inliers < 3 or q.ransac_iterations < 1:
            raise ConfigError(
                "registration.place: need orb_features >= 10, candidates >= 1, min_inliers >= 3 "
                "and ransac_iterations >= 1"
            )

        r = self.relocalise
        if (
            r.orb_features < 10
            or r.vote_features < 1
            or r.vote_keyframes < 1
            or r.candidates < 1
            or r.ransac_iterations < 1
            or r.reinit_after < 1
            or r.merge_every < 1
            or r.merge_every_behind < 1
        ):
            raise ConfigError(
                "registration.relocalise: need orb_features >= 10, vote_features, "
                "vote_keyframes, candidates, ransac_iterations, reinit_after, merge_every and "
                "merge_every_behind >= 1"
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
