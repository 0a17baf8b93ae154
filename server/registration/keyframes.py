"""The keyframes a frame is registered against, and keyframe changes: when one is due, going
back to an earlier keyframe that sees the view, and the pose of a frame about to become a new
keyframe, solved against several recent ones."""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from server.geometry import (
    Intrinsics,
    adjoint,
    exp_se3,
    invert,
    orthonormalize,
    pose_distance,
    rotation_angle_deg,
)
from server.geometry.arrays import Float32Array, FloatArray, GreyImage
from server.registration.config import KeyframeConfig, RegistrationConfig
from server.registration.frame_to_keyframe import Registration, Tracks, judge, track_keyframe
from server.registration.keyframe import Keyframe, make_keyframe
from server.registration.results import TrackingState, TrackResult
from server.registration.sparse import (
    gauss_newton_step,
    information,
    point_information,
    robust_equations,
)

log = logging.getLogger(__name__)


class Keyframes:
    """The tracker's keyframes: the ``current`` one, the ``recent`` ones (newest last) and those of
    a saved map (``map``, a room's) this session continues in; ``count`` have been made here (or
    taken from a map), the next one's id."""

    def __init__(self, K: Intrinsics, cfg: RegistrationConfig) -> None:
        self.K, self.cfg = K, cfg
        self.current: Keyframe | None = None
        self.recent: deque[Keyframe] = deque(maxlen=cfg.keyframes.recent_keyframes)
        self.map: list[Keyframe] = []
        self.count = 0

    def held(self) -> list[Keyframe]:
        """Every keyframe held: the current one, the recent ones, a saved map's."""
        return [k for k in [self.current, *self.recent, *self.map] if k is not None]

    def make(
        self, index: int, T_world_camera: FloatArray, grey: GreyImage, depth: Float32Array
    ) -> Keyframe:
        """Frame ``index`` as a keyframe at T_world_camera (4x4, metres; depth cleaned, metres),
        not held yet (``add``)."""
        return make_keyframe(self.count, index, T_world_camera, grey, depth, self.K, self.cfg)

    def add(self, kf: Keyframe, segment: int) -> Keyframe | None:
        """Make ``kf`` (of map segment ``segment``) the current keyframe and the newest recent
        one; returns the recent keyframe it pushes out, if any."""
        self.count += 1
        kf.segment = segment
        self.current = kf
        left = self.recent[0] if len(self.recent) == self.recent.maxlen else None
        self.recent.append(kf)
        return left

    def resume(self, keyframe: Keyframe, map_keyframes: list[Keyframe]) -> None:
        """Hold a saved map's keyframes (in the map, segment 0) instead, ``keyframe`` current."""
        self.map = list(map_keyframes)
        for kf in self.map:
            kf.segment = 0
        self.recent.clear()
        self.recent.append(keyframe)
        self.current = keyframe
        self.count = max(k.id for k in [keyframe, *self.map]) + 1

    def switch(self, segment: int, p: PendingKeyframe) -> tuple[Keyframe, Tracks] | None:
        """Go back to an earlier keyframe of ``segment`` that sees the pending frame's view
        (``switch_keyframe``): it becomes current. Returns it and its corners followed into the
        frame, or None (no switch)."""
        args = (p.grey, p.depth, p.T_world_camera, self.K, self.cfg)
        switched = switch_keyframe(self.recent, self.map, self.current, segment, *args)
        if switched is not None:
            self.current = switched[0]
        return switched


@dataclass
class PendingKeyframe:
    """A keyframe change that ``Tracker.track`` found due, for ``update_keyframe`` to make."""

    index: int
    grey: GreyImage
    depth: Float32Array  # cleaned, metres
    T_world_camera: FloatArray
    result: TrackResult  # updated in place when the change is made
    registration: Registration | None = None  # against the current keyframe


VGA_PIXELS = 640 * 480  # the image size KeyframeConfig.min_tracked is set for


def min_tracked(kf: Keyframe, c: KeyframeConfig) -> float:
    """The fewest of ``kf``'s corners a frame must still follow, whatever their share:
    ``c.min_tracked`` for a 640x480 image (and larger), less for a smaller one, by the square
    root of its share of the area. A phone's live AR view (640x288) keeps about half the corners
    a 640x480 view does (89 against 170 on 7scenes_a), so the VGA floor alone made a new
    keyframe due on a quarter of its frames (74 of 300, all by the floor; 22 of 300 at
    640x480). At the 640x288 crop the floor is 62: keyframes 134 -> 109 on tum_fr1_xyz (ATE
    2.36 -> 2.19 cm), 156 -> 87 on 7scenes_a (4.44 -> 4.44 cm), synthetic_room0 unchanged; in
    proportion to the area (48) 7scenes_a drifted to 5.26 cm. 640x480 images are unchanged."""
    height, width = kf.grey.shape[:2]
    return float(c.min_tracked * min(1.0, width * height / VGA_PIXELS) ** 0.5)


def needs_keyframe(kf: Keyframe, T_kf_cur: FloatArray, tracked: int, c: KeyframeConfig) -> bool:
    """A keyframe change is due: too few of ``kf``'s corners still followed (``tracked``), or
    the camera too far from it (T_kf_cur, 4x4, metres)."""
    return (
        tracked < max(min_tracked(kf, c), c.min_tracked_ratio * len(kf.points))
        or float(np.linalg.norm(T_kf_cur[:3, 3])) > c.max_translation_m
        or rotation_angle_deg(T_kf_cur) > c.max_rotation_deg
    )


def switch_keyframe(
    recent: Iterable[Keyframe],
    map_keyframes: Iterable[Keyframe],
    current: Keyframe | None,
    segment: int,
    grey: GreyImage,
    depth: Float32Array,
    T_world_cur: FloatArray,
    K: Intrinsics,
    cfg: RegistrationConfig,
) -> tuple[Keyframe, Tracks] | None:
    """Go back to an earlier keyframe of this segment (a recent one or a saved map's) that sees
    this view well (depth: cleaned, metres; T_world_cur: 4x4, metres), instead of making a new
    one: every new keyframe adds its own error to the chain, an old one adds none. Returns that
    keyframe and its corners followed into this frame, or None."""
    c = cfg.keyframes
    in_segment = [k for k in recent if k.segment == segment]
    candidates = in_segment + [
        k for k in map_keyframes if k.segment == segment and all(k is not r for r in in_segment)
    ]
    near = sorted(candidates, key=lambda k: pose_distance(k.T_world_keyframe, T_world_cur))
    if c.switch_order == "oldest":
        near.sort(key=lambda k: k.id)
    tries = 0
    for kf in near:
        if kf is current:
            continue
        if tries == c.switch_tries:
            break
        T_kf_cur = invert(kf.T_world_keyframe) @ T_world_cur
        if np.linalg.norm(T_kf_cur[:3, 3]) > c.switch_reach * c.max_translation_m:
            if c.switch_order == "nearest":
                break
            continue
        if rotation_angle_deg(T_kf_cur) > c.switch_reach * c.max_rotation_deg:
            continue
        tries += 1
        reg = track_keyframe(kf, grey, depth, T_world_cur, K, cfg)
        if reg is None or judge(reg.solution, cfg.state) is not TrackingState.OK:
            continue
        keep = reg.surviving()
        need = c.switch_tracked_factor * c.min_tracked_ratio * len(kf.points)
        if keep.sum() < max(min_tracked(kf, c), need):
            continue
        return kf, Tracks(reg.ids[keep], reg.uv[keep], grey)
    return None


def refine_in_window(
    recent: Iterable[Keyframe],
    grey: GreyImage,
    depth: Float32Array,
    T_world_cur: FloatArray,
    reg: Registration,
    K: Intrinsics,
    cfg: RegistrationConfig,
    window: int | None = None,
) -> FloatArray:
    """The pose of a frame about to become a keyframe, solved jointly against the current
    keyframe and up to ``window`` (None: ``keyframes.window``) other ``recent`` ones (newest
    last, as the tracker holds them).

    The current keyframe's estimate (``reg``) enters as a quadratic prior (its sparse information
    about ``T_world_cur``, which may carry the dense refinement); each other keyframe that
    registers the frame ok adds its sparse terms. A new keyframe then hangs on several older ones
    instead of one, so one poor registration no longer passes all its error down the chain.
    """
    c = cfg.keyframes
    window = c.window if window is None else window
    others: list[Registration] = []
    for kf in reversed(list(recent)):
        if len(others) >= window:
            break
        if kf is reg.kf or kf.segment != reg.kf.segment:
            continue
        T_kf_cur = invert(kf.T_world_keyframe) @ T_world_cur
        if (
            float(np.linalg.norm(T_kf_cur[:3, 3])) > c.window_reach * c.max_translation_m
            or rotation_angle_deg(T_kf_cur) > c.window_reach * c.max_rotation_deg
        ):
            continue
        found = track_keyframe(kf, grey, depth, T_world_cur, K, cfg)
        # A weak registration (few inliers) still adds what it knows: its information says
        # how little that is.
        if found is not None and judge(found.solution, cfg.state) is not TrackingState.LOST:
            others.append(found)
            log.debug("window: keyframe %d adds %d inliers", kf.id, found.solution.inliers.sum())
    if not others:
        return T_world_cur
    # The current keyframe's information about the pose, moved to world-frame twists.
    A0 = adjoint(invert(reg.kf.T_world_keyframe))
    H0 = A0.T @ reg.solution.equations.H @ A0
    # Each other keyframe's inlier points and covariances, fixed over the iterations.
    terms = []
    for o in others:
        with_depth = o.ids[o.with_depth][o.solution.inliers]
        Q = o.points[o.solution.inliers]
        T_keyframe_world = invert(o.kf.T_world_keyframe)
        terms.append(
            (
                o.kf.points[with_depth],
                o.kf.covariances[with_depth],
                Q,
                point_information(Q, K, cfg.depth),
                T_keyframe_world,
                adjoint(T_keyframe_world),
            )
        )
    T: FloatArray = T_world_cur.copy()
    xi_total = np.zeros(6)
    for _ in range(cfg.solver.max_iterations):
        H, g = H0.copy(), H0 @ xi_total
        for P, cov_P, Q, cov_Q, T_keyframe_world, A in terms:
            T_kf_cur = T_keyframe_world @ T
            W = information(cov_P, cov_Q, T_kf_cur[:3, :3])
            eq = robust_equations(P, Q, W, T_kf_cur, cfg.solver, reject=True)[0]
            H += A.T @ eq.H @ A
            g += A.T @ eq.g
        xi = gauss_newton_step(H, g)
        T = orthonormalize(exp_se3(xi) @ T)
        xi_total += xi
        if np.linalg.norm(xi) < cfg.solver.convergence_step:
            break
    return T
