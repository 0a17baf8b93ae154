"""The per-frame registration pipeline: track corners, solve the pose, refine, manage keyframes.

Read ``Tracker.track`` top to bottom: it follows the paper's section III with the additions that
make it hold up on real hand-held data (keyframes, robust weights, a tracking state, recovery).

A frame is registered in two phases, so that a live session can publish the pose before the
slower keyframe work: :meth:`Tracker.track` returns the pose and says whether a keyframe change
is due; :meth:`Tracker.update_keyframe` then switches to an old keyframe or builds a new one.
"""

from __future__ import annotations

import logging
import time
from collections import deque
from dataclasses import dataclass, field, replace
from enum import Enum

import numpy as np

from server.geometry import (
    Intrinsics,
    adjoint,
    backproject_pixels,
    exp_se3,
    invert,
    orthonormalize,
    pose_distance,
    project,
    rotation_angle_deg,
)
from server.geometry.arrays import BoolArray, Float32Array, FloatArray, GreyImage, IndexArray
from server.registration.config import RegistrationConfig
from server.registration.dense import DenseModel, refine_dense, sample_dense_points
from server.registration.flow import track_points
from server.registration.keyframe import Keyframe, make_keyframe
from server.registration.place import KeyframeDatabase, PlaceFeatures
from server.registration.preprocess import (
    clean_depth,
    sample_stable_depth,
    to_grey,
)
from server.registration.prior import DeviceAlignment, prior_motion
from server.registration.relocalise import (
    Relocalisation,
    Relocaliser,
    align_to_surface,
    corrected,
)
from server.registration.sparse import (
    NormalEquations,
    SparseSolution,
    information,
    mahalanobis,
    point_information,
    robust_weights,
    solve_sparse,
    sparse_equations,
)

log = logging.getLogger(__name__)


class TrackingState(str, Enum):
    """How far a frame's pose can be trusted."""

    OK = "ok"
    WEAK = "weak"  # pose estimated from few or poorly fitting correspondences
    LOST = "lost"  # no pose: the last good one is held


@dataclass
class TrackResult:
    """The outcome of registering one frame."""

    index: int
    T_world_camera: FloatArray  # 4x4, metres; the last good pose when state is LOST
    state: TrackingState
    inliers: int
    rmse: float  # Mahalanobis RMSE of the sparse inliers
    condition: float  # scaled conditioning of J^T W J, 0 = degenerate
    keyframe_id: int  # the keyframe this frame is tracked against, or, after update_keyframe,
    # the one the next frame will be tracked against
    new_keyframe: bool  # this frame became a keyframe (set by update_keyframe, or at the start)
    timings_ms: dict[str, float] = field(default_factory=dict)
    keyframe_due: bool = False  # track() left a keyframe switch or a new keyframe pending
    prior_used: bool = False  # the initial guess came from the device's own pose
    # "colour", "depth" or "both": this frame repeats the previous frame's image(s) and was held
    # at that frame's pose, not tracked (state.hold_repeated_frames); None for a tracked frame.
    repeated: str | None = None
    # The map segment the pose is in: 0 is the map; another one is a segment started after a
    # loss that nothing recovered, placed by the motion model only (state WEAK) until it merges.
    segment: int = 0
    # Set on the frame that merged a segment into the map: (segment, T_correction), the 4x4
    # that moved the segment's poses into the map (T_map = T_correction @ T_segment).
    merged: tuple[int, FloatArray] | None = None
    relocalised: bool = False  # found again by place recognition after flow failed

    @property
    def recovery(self) -> str | None:
        """How this frame recovers from a loss, as the wire says it: "relocalised" (found again
        by place recognition), "merged" (its segment merged into the map here), "segment" (in a
        segment not merged yet), or None (tracked as usual, or lost)."""
        if self.merged is not None:
            return "merged"
        if self.relocalised:
            return "relocalised"
        if self.segment != 0 and self.state is not TrackingState.LOST:
            return "segment"
        return None

    @property
    def fusable(self) -> bool:
        """Its images and its pose belong together, so it may go into a map: tracked (not lost),
        not a held repeat (whose colour and depth are of two moments), and in the map (not in a
        segment whose place in it is a guess)."""
        return self.state is not TrackingState.LOST and self.repeated is None and self.segment == 0


@dataclass
class _PendingKeyframe:
    """A keyframe change that ``track`` found due, for ``update_keyframe`` to carry out."""

    index: int
    grey: GreyImage
    depth: Float32Array  # cleaned, metres
    T_world_camera: FloatArray
    result: TrackResult  # updated in place when the change is made
    registration: _Registration | None = None  # against the current keyframe


@dataclass
class _Tracks:
    """Corners of the current keyframe still followed, and where they were last seen."""

    ids: IndexArray  # indices into the keyframe's corners
    uv: Float32Array  # (N, 2) pixels in ``grey``
    grey: GreyImage  # the frame they were last seen in


@dataclass
class _Registration:
    """Corners of ``kf`` found in the current frame and the pose they give.

    ids, uv: keyframe corner indices and their pixels here, for every corner LK followed.
    with_depth: which of them have trusted depth here; ``points`` and ``solution`` cover those.
    """

    kf: Keyframe
    ids: IndexArray
    uv: Float32Array
    with_depth: BoolArray
    points: FloatArray
    solution: SparseSolution
    guess_from_prior: bool = False  # started from the device's pose, not constant velocity

    def surviving(self) -> BoolArray:
        """Corners worth following on: tracked, and not an outlier where depth was available.
        A corner on a depth hole is kept, as the next frame may measure it."""
        keep = ~self.with_depth
        keep[np.flatnonzero(self.with_depth)[self.solution.inliers]] = True
        return keep


class Tracker:
    """Frame-to-keyframe RGB-D odometry (FAST + pyramidal LK + Gauss-Newton on SE(3)).

    Feed frames in order to :meth:`track`; poses are T_world_camera with the first frame at
    ``T_world_first`` (identity by default). The world is the map. Call :meth:`update_keyframe`
    after each ``track`` (once the pose is sent): otherwise the next ``track`` does it first,
    which gives the same trajectory but leaves the earlier result's ``new_keyframe`` unknown to
    its caller. A frame may carry the device's own pose as a prior (see ``track``);
    ``T_world_device`` then says where the device's world lies in the map.
    """

    def __init__(
        self,
        intrinsics: Intrinsics,
        config: RegistrationConfig | None = None,
        T_world_first: FloatArray | None = None,
    ) -> None:
        self.K = intrinsics
        self.cfg = config or RegistrationConfig()
        self.T_world_first: FloatArray = (
            np.eye(4) if T_world_first is None else T_world_first.copy()
        )
        self.keyframe: Keyframe | None = None
        self.recent: deque[Keyframe] = deque(maxlen=self.cfg.keyframes.recent_keyframes)
        self.tracks: _Tracks | None = None
        self.T_world_last: FloatArray = self.T_world_first.copy()
        self.velocity: FloatArray = np.eye(4)  # T_previous_last: motion over the last frame
        self.lost = False
        self.frame_count = 0
        self.keyframe_count = 0
        self.pending: _PendingKeyframe | None = None
        self.alignment = DeviceAlignment(self.cfg.prior)
        self.device_last: FloatArray | None = None  # the prior of the last tracked frame
        self.device_world = 0  # the device's world the priors are in (track)
        # Keyframes of a saved map (a room) this session continues in: candidates for a keyframe
        # switch beside the recent ones, so that tracking goes back to the map where it can.
        self.map_keyframes: list[Keyframe] = []
        # The previous frame's images as given (to tell a repeated one), the last result, and
        # how many frames have been held since the last tracked one.
        self._previous: tuple[GreyImage, Float32Array] | None = None
        self._last_result: TrackResult | None = None
        self.held = 0
        # Recovery (relocalise config): every keyframe's place features; the map segment being
        # tracked (0: the map), how many were started, where the current one started, frames
        # lost in a row, and the motion before the loss (to carry the pose over a new segment).
        self.relocaliser = Relocaliser(intrinsics, self.cfg)
        self.segment = 0
        self.segments_started = 0
        self._segment_start = 0
        self.lost_run = 0
        self._velocity_before_loss: FloatArray = np.eye(4)
        self.archive: dict[int, Keyframe] = {}  # older keyframes by id, oldest first (_archive)
        # The last frame's place features, with the grey image they describe (compared by
        # identity: frame indices may start again): a lost frame is looked up and may then
        # become a keyframe, which would describe it a second time (~8 ms of ORB).
        self._described: tuple[GreyImage, PlaceFeatures] | None = None

    @property
    def T_world_device(self) -> FloatArray | None:
        """The device's world frame in the map (4x4, metres), once a frame with a prior tracked
        ok; None before. Maps a device-world point into the map: p_world = T @ p_device."""
        return (
            None if self.alignment.T_world_device is None else self.alignment.T_world_device.copy()
        )

    def resume_in_map(
        self,
        T_world_camera: FloatArray,
        keyframe: Keyframe,
        map_keyframes: list[Keyframe],
        places: KeyframeDatabase | None = None,
    ) -> None:
        """Continue in a saved map: the next frame is tracked against ``keyframe`` (one of
        ``map_keyframes``, in the map's world frame) from ``T_world_camera`` (4x4, metres; e.g.
        from place recognition), with its corners followed straight from the keyframe image.
        ``map_keyframes`` stay candidates for keyframe switches; new keyframes get ids above
        theirs. ``places``: the map's place database, which a later loss looks up too. Whatever
        was tracked before is dropped."""
        self.map_keyframes = list(map_keyframes)
        for kf in self.map_keyframes:
            kf.segment = 0
        self.relocaliser = Relocaliser(self.K, self.cfg)
        self.archive.clear()
        for entry in places.entries if places is not None else []:
            self.relocaliser.add(entry.keyframe_id, 0, entry.T_world_keyframe, entry.features)
        self.segment = 0
        self.lost_run = 0
        self.recent.clear()
        self.recent.append(keyframe)
        self.keyframe = keyframe
        self.keyframe_count = max(k.id for k in [keyframe, *self.map_keyframes]) + 1
        self.tracks = None
        self.pending = None
        self.T_world_last = orthonormalize(np.asarray(T_world_camera, dtype=np.float64))
        self.velocity = np.eye(4)
        self.held = 0
        self.lost = False
        self.device_last = None
        self.alignment.reset()

    def apply_correction(
        self, keyframe_poses: dict[int, FloatArray], T_correction: FloatArray
    ) -> None:
        """Move the tracker into a corrected world (loop closure), between two frames.

        ``keyframe_poses``: corrected T_world_keyframe (4x4, metres) per keyframe id, for the
        keyframes the pose graph knows; every other keyframe held here (newer than the graph)
        and the last pose move by ``T_correction`` (old world to new world, 4x4:
        T_new = T_correction @ T_old). The velocity is a motion in the camera's own frame
        (T_previous_last), the same in either world. The device prior's alignment to the map
        is void and starts again; the corners followed stay as they are (they live in images).
        """
        T_correction = np.asarray(T_correction, dtype=np.float64)
        seen: set[int] = set()
        held = [self.keyframe, *self.recent, *self.map_keyframes, *self.archive.values()]
        for kf in held:
            if kf is None or id(kf) in seen:
                continue
            seen.add(id(kf))
            kf.T_world_keyframe = corrected(
                kf.T_world_keyframe, keyframe_poses.get(kf.id), T_correction
            )
        self.relocaliser.correct(keyframe_poses, T_correction)
        self.T_world_last = orthonormalize(T_correction @ self.T_world_last)
        self.T_world_first = orthonormalize(T_correction @ self.T_world_first)
        if self.pending is not None:  # a keyframe change found due and not yet made
            self.pending.T_world_camera = orthonormalize(T_correction @ self.pending.T_world_camera)
        self.alignment.reset()

    # ------------------------------------------------------------------ per frame
    def track(
        self,
        colour: GreyImage,
        depth: Float32Array,
        T_device_camera: FloatArray | None = None,
        device_world: int = 0,
    ) -> TrackResult:
        """Register one frame: colour (H, W, 3) RGB uint8, depth (H, W) metres (0 = none).

        ``T_device_camera`` (optional, 4x4, metres): the device's own estimate of this camera's
        pose in the device's world frame (e.g. ARCore/ARKit odometry), camera axes x right,
        y down, z forward. Its motion since the last tracked frame, applied to that frame's pose,
        is the initial guess (instead of constant velocity) and is tried first after a loss;
        the result stays in the map frame. A non-finite prior is ignored.

        ``device_world``: which of the device's worlds the prior is in. A device whose own
        tracking restarted or relocalised (ARCore after a loss) says so with a new number: the
        prior's step across the change is no motion (its world jumped), so it is not used, and
        where the device's world lies in the map is found again.

        Returns as soon as the pose T_world_camera is accepted; a keyframe change it calls for is
        only recorded (``keyframe_due``), for :meth:`update_keyframe`. The very first frame (and
        a restart after a failed first frame) builds its keyframe here, as its state depends on it.
        """
        if self.pending is not None:
            self.update_keyframe()  # the caller skipped it: keep the trajectory the same
        index = self.frame_count
        self.frame_count += 1
        t0 = time.perf_counter()
        grey = to_grey(colour)
        prior = self._check_prior(T_device_camera)
        if device_world != self.device_world:
            self.device_world = device_world
            self.device_last = None
            self.alignment.reset()
        repeated = self._repeated(grey, depth)
        if repeated is not None and self._last_result is not None and not self.lost:
            return self._hold(index, repeated, {"preprocess": _ms(t0)}, prior)
        self._last_result = self._register(index, grey, depth, prior, t0)
        return self._last_result

    def _register(
        self,
        index: int,
        grey: GreyImage,
        depth: Float32Array,
        prior: FloatArray | None,
        t0: float,
    ) -> TrackResult:
        """Steps 1-5 for a frame that is not a held repeat (``track``): depth as given, metres."""
        depth = clean_depth(depth, self.cfg.depth)
        timings = {"preprocess": _ms(t0)}

        if self.keyframe is None:
            return self._start(index, grey, depth, timings, prior)

        # 1. Predict the pose: by the device's own motion when it sends one, else with a
        # constant-velocity model (also the fallback when the prior's guess fails), over the
        # frames held since the last tracked one too.
        gap, self.held = 1 + self.held, 0
        T_world_pred = orthonormalize(
            self.T_world_last @ np.linalg.matrix_power(self.velocity, gap)
        )
        T_world_prior = self._prior_guess(prior)

        # 2-3. Track corners (from the previous frame, or from keyframes after a loss), solve.
        t = time.perf_counter()
        if self.lost:
            found = self._relocalise(grey, depth, T_world_pred, T_world_prior)
        else:
            found = None
            if T_world_prior is not None:
                found = self._track_keyframe(self.keyframe, grey, depth, T_world_prior, True)
                if found is None or self._judge(found.solution) is TrackingState.LOST:
                    found = None  # a wrong prior: try the guess without it
                else:
                    found.guess_from_prior = True
            if found is None:
                found = self._track_keyframe(self.keyframe, grey, depth, T_world_pred, True)
        timings["sparse"] = _ms(t)
        state = None if found is None else self._judge(found.solution)
        relocalised = False
        if state in (None, TrackingState.LOST):
            # 3b. Flow found nothing: look the frame up among every keyframe, in this frame.
            t = time.perf_counter()
            recovered = self._recover(grey, depth)
            timings["relocalise"] = _ms(t)
            if isinstance(recovered, Relocalisation):
                restarted = self._restart_at_place(index, grey, depth, timings, recovered)
                if restarted is not None:
                    return restarted
            elif recovered is not None:
                found, state, relocalised = recovered, self._judge(recovered.solution), True
        if state in (None, TrackingState.LOST) and prior is not None and T_world_prior is not None:
            # 3c. Not found in the map either: the device's pose carries tracking on (its drift
            # over the gap enters the map, so it comes after place recognition).
            resumed = self._resume_from_prior(index, grey, depth, timings, prior, T_world_prior)
            if resumed is not None:
                return resumed
        if found is None or state is None or state is TrackingState.LOST:
            n, rmse, cond = (0, np.inf, 0.0) if found is None else _quality(found.solution)
            lost = self._lose(index, grey, timings, n, rmse, cond)
            if self.lost_run >= self.cfg.relocalise.reinit_after and self.cfg.relocalise.enabled:
                started = self._start_segment(index, grey, depth, timings)
                if started is not None:
                    return started
            return lost
        kf, solution = found.kf, found.solution

        # 4. Dense refinement from the sparse estimate.
        T_kf_cur = solution.T
        if self.cfg.solver.dense and kf.dense is not None:
            t = time.perf_counter()
            T_kf_cur = self._refine(found, kf.dense, depth, grey)
            timings["dense"] = _ms(t)

        # 5. Accept the pose, keep the surviving tracks, and note whether a keyframe change is due.
        T_world_cur = orthonormalize(kf.T_world_keyframe @ T_kf_cur)
        if self.lost or relocalised:
            self.velocity = np.eye(4)
        elif gap == 1:  # after held frames the motion spans several frames: keep the old one
            self.velocity = invert(self.T_world_last) @ T_world_cur
        self.lost, self.lost_run = False, 0
        # 6. In a segment: now and then, look for the map; found, the segment moves into it.
        merged = None
        if (
            self.segment != 0
            and (index - self._segment_start) % self.cfg.relocalise.merge_every == 0
        ):
            t = time.perf_counter()
            merged = self._merge_segment(grey, depth, T_world_cur)
            timings["merge"] = _ms(t)
            if merged is not None:
                T_world_cur = orthonormalize(merged[1] @ T_world_cur)
        self.T_world_last = T_world_cur
        if self.segment != 0 and state is TrackingState.OK:
            state = TrackingState.WEAK  # tracked, but where the segment lies is a guess
        self.keyframe = kf
        self.device_last = prior
        if prior is not None and state is TrackingState.OK:
            self.alignment.add(T_world_cur, prior)
        keep = found.surviving()
        self.tracks = _Tracks(found.ids[keep], found.uv[keep], grey)
        due = self._needs_keyframe(kf, T_kf_cur, len(self.tracks.ids))
        timings["total"] = _ms(t0)
        result = TrackResult(
            index,
            T_world_cur.copy(),
            state,
            *_quality(solution),
            kf.id,
            False,
            timings,
            keyframe_due=due,
            prior_used=found.guess_from_prior,
            segment=self.segment,
            merged=merged,
            relocalised=relocalised,
        )
        if due:
            self.pending = _PendingKeyframe(index, grey, depth, T_world_cur, result, found)
        return result

    def update_keyframe(self) -> bool:
        """Carry out the keyframe change the last :meth:`track` found due: go back to an earlier
        keyframe that sees this view, else make this frame a new keyframe.

        Returns True when a new keyframe was made. The last result is updated in place:
        ``new_keyframe``, ``keyframe_id`` (the keyframe the next frame is tracked against),
        ``keyframe_due`` cleared, ``timings_ms["keyframe"]`` added to ``timings_ms["total"]``.
        Does nothing (False) when no change is due, e.g. a second call.
        """
        p, self.pending = self.pending, None
        if p is None:
            return False
        t = time.perf_counter()
        kf = self._switch_keyframe(p.grey, p.depth, p.T_world_camera)
        new_kf = kf is None
        if kf is None:
            T_world_kf = p.T_world_camera
            if self.cfg.keyframes.window > 0 and p.registration is not None:
                T_world_kf = self._refine_in_window(p.grey, p.depth, T_world_kf, p.registration)
                self.T_world_last = T_world_kf
            kf = self._new_keyframe(p.index, p.grey, p.depth, T_world_kf)
        ms = _ms(t)
        r = p.result
        r.new_keyframe, r.keyframe_id, r.keyframe_due = new_kf, kf.id, False
        r.timings_ms["keyframe"] = ms
        r.timings_ms["total"] = r.timings_ms.get("total", 0.0) + ms
        return new_kf

    # ------------------------------------------------------------------ stages
    def _repeated(self, grey: GreyImage, depth: Float32Array) -> str | None:
        """Which of this frame's images are the very same as the previous frame's: "colour",
        "depth", "both" or None (state.hold_repeated_frames; None when that is off)."""
        if not self.cfg.state.hold_repeated_frames:
            return None
        previous = self._previous
        # Copies: a caller may refill its own buffers with the next frame.
        self._previous = (grey.copy(), np.array(depth, copy=True))
        if previous is None:
            return None
        same_colour = previous[0].shape == grey.shape and np.array_equal(previous[0], grey)
        same_depth = previous[1].shape == depth.shape and np.array_equal(previous[1], depth)
        if same_colour and same_depth:
            return "both"
        return "colour" if same_colour else "depth" if same_depth else None

    def _hold(
        self, index: int, repeated: str, timings: dict[str, float], prior: FloatArray | None
    ) -> TrackResult:
        """A repeated frame: the previous frame's state and pose, moved by the device's own
        motion since then when the frame carries a prior (its camera did move, and AR draws on
        this frame); nothing tracked, and the tracker goes on from the last tracked frame."""
        last = self._last_result
        assert last is not None
        self.held += 1
        T_prior = self._prior_guess(prior)
        timings["total"] = sum(timings.values())
        kf_id = self.keyframe.id if self.keyframe is not None else last.keyframe_id
        return TrackResult(
            index,
            self.T_world_last.copy() if T_prior is None else T_prior,
            last.state,
            last.inliers,
            last.rmse,
            last.condition,
            kf_id,
            False,
            timings,
            prior_used=T_prior is not None,
            repeated=repeated,
            segment=self.segment,
        )

    def _check_prior(self, T_device_camera: FloatArray | None) -> FloatArray | None:
        """The prior to use for this frame, or None (none sent, disabled, or not finite)."""
        if T_device_camera is None or not self.cfg.prior.enabled:
            return None
        T = np.asarray(T_device_camera, dtype=np.float64)
        if T.shape != (4, 4):
            raise ValueError(f"T_device_camera must be 4x4, got shape {T.shape}")
        if not np.isfinite(T).all():
            log.debug("non-finite device pose ignored")
            return None
        return orthonormalize(T)

    def _prior_guess(self, prior: FloatArray | None) -> FloatArray | None:
        """T_world_camera by the prior: its motion since the last tracked frame applied to that
        frame's pose; or, when that frame had no prior, the prior moved into the map."""
        if prior is None:
            return None
        if self.device_last is not None:
            motion = prior_motion(self.device_last, prior, self.cfg.prior)
            if motion is not None:
                return orthonormalize(self.T_world_last @ motion)
            # The device's world jumped: its alignment to the map is void.
            log.info("device pose jumped: prior ignored, alignment reset")
            self.alignment.reset()
            self.device_last = None
            return None
        T_world_device = self.alignment.T_world_device
        return None if T_world_device is None else orthonormalize(T_world_device @ prior)

    def _start(
        self,
        index: int,
        grey: GreyImage,
        depth: Float32Array,
        timings: dict[str, float],
        prior: FloatArray | None,
    ) -> TrackResult:
        t = time.perf_counter()
        kf = self._new_keyframe(index, grey, depth, self.T_world_first)
        timings["keyframe"] = _ms(t)
        # A first frame without texture or depth cannot anchor tracking.
        state = (
            TrackingState.OK if len(kf.points) >= self.cfg.state.ok_inliers else TrackingState.LOST
        )
        if state is TrackingState.LOST:
            self.keyframe, self.lost = None, True
            self.recent.clear()
            self.relocaliser = Relocaliser(self.K, self.cfg)
        else:
            self.device_last = prior
            if prior is not None:
                self.alignment.add(self.T_world_first, prior)
        return TrackResult(
            index,
            self.T_world_first.copy(),
            state,
            len(kf.points),
            0.0,
            1.0,
            kf.id,
            state is TrackingState.OK,
            timings,
        )

    def _track_keyframe(
        self,
        kf: Keyframe,
        grey: GreyImage,
        depth: Float32Array,
        T_world_pred: FloatArray,
        chained: bool,
    ) -> _Registration | None:
        """Track the keyframe's corners into this frame and solve T_keyframe_current.

        ``chained`` follows the corners from the previous frame (small steps); otherwise they are
        tracked straight from the keyframe image (after a loss)."""
        T_kf_pred = invert(kf.T_world_keyframe) @ T_world_pred
        if chained and self.tracks is not None and len(self.tracks.ids) > 0:
            ids, uv_from, grey_from = self.tracks.ids, self.tracks.uv, self.tracks.grey
        else:
            ids, uv_from, grey_from = np.arange(len(kf.uv)), kf.uv, kf.grey
        if len(ids) < self.cfg.state.lost_inliers:
            return None
        # Where the prediction puts the corners in this frame: the start of the LK search.
        T_cur_kf = invert(T_kf_pred)
        guess, z = project(kf.points[ids] @ T_cur_kf[:3, :3].T + T_cur_kf[:3, 3], self.K)
        guess = np.where(np.isfinite(guess) & (z[:, None] > 0), guess, uv_from)
        uv, ok = track_points(grey_from, grey, uv_from, self.cfg.flow, guess)
        ids, uv = ids[ok], uv[ok]
        if grey_from is not kf.grey and self.cfg.flow.keyframe_refine_levels >= 0 and len(ids):
            ids, uv = self._refine_from_keyframe(kf, grey, ids, uv)
        zc = sample_stable_depth(depth, uv, self.cfg.depth)
        with_depth = zc > 0
        if with_depth.sum() < self.cfg.state.lost_inliers:
            return None
        d_ids = ids[with_depth]
        Q = backproject_pixels(uv[with_depth].astype(np.float64), zc[with_depth], self.K)
        solution = solve_sparse(
            kf.points[d_ids],
            Q,
            kf.covariances[d_ids],
            point_information(Q, self.K, self.cfg.depth),
            T_kf_pred,
            self.cfg.solver,
        )
        return _Registration(kf, ids, uv, with_depth, Q, solution)

    def _refine_from_keyframe(
        self, kf: Keyframe, grey: GreyImage, ids: IndexArray, uv: Float32Array
    ) -> tuple[IndexArray, Float32Array]:
        """Re-align chained tracks straight against the keyframe image (flow.keyframe_refine_*):
        LK from the keyframe's corners, starting where the chain put them; a track that moves
        more than ``keyframe_refine_max_px`` or fails the forward-backward check is dropped."""
        f = self.cfg.flow
        cfg = replace(f, pyramid_levels=f.keyframe_refine_levels, fb_pyramid_levels=0)
        uv_kf, ok = track_points(kf.grey, grey, kf.uv[ids], cfg, uv)
        ok &= np.linalg.norm(uv_kf - uv, axis=1) <= f.keyframe_refine_max_px
        return ids[ok], uv_kf[ok]

    def _refine_in_window(
        self, grey: GreyImage, depth: Float32Array, T_world_cur: FloatArray, reg: _Registration
    ) -> FloatArray:
        """The pose of a frame about to become a keyframe, solved jointly against the current
        keyframe and up to ``keyframes.window`` other recent ones (keyframes.window).

        The current keyframe's estimate enters as a quadratic prior (its sparse information about
        ``T_world_cur``, which may carry the dense refinement); each other keyframe that registers
        the frame ok adds its sparse terms. A new keyframe then hangs on several older ones
        instead of one, so one poor registration no longer passes all its error down the chain.
        """
        c = self.cfg.keyframes
        others: list[_Registration] = []
        for kf in reversed(self.recent):
            if len(others) >= c.window:
                break
            if kf is reg.kf or kf.segment != reg.kf.segment:
                continue
            T_kf_cur = invert(kf.T_world_keyframe) @ T_world_cur
            if (
                float(np.linalg.norm(T_kf_cur[:3, 3])) > c.window_reach * c.max_translation_m
                or rotation_angle_deg(T_kf_cur) > c.window_reach * c.max_rotation_deg
            ):
                continue
            found = self._track_keyframe(kf, grey, depth, T_world_cur, chained=False)
            # A weak registration (few inliers) still adds what it knows: its information says
            # how little that is.
            if found is not None and self._judge(found.solution) is not TrackingState.LOST:
                others.append(found)
                log.debug(
                    "window: keyframe %d adds %d inliers", kf.id, found.solution.inliers.sum()
                )
        if not others:
            return T_world_cur
        # The current keyframe's information about the pose, moved to world-frame twists.
        A0 = adjoint(invert(reg.kf.T_world_keyframe))
        H0 = A0.T @ reg.solution.equations.H @ A0
        T: FloatArray = T_world_cur.copy()
        xi_total = np.zeros(6)
        for _ in range(self.cfg.solver.max_iterations):
            H, g = H0.copy(), H0 @ xi_total
            for o in others:
                inl = o.solution.inliers
                P = o.kf.points[o.ids[o.with_depth][inl]]
                cov_P = o.kf.covariances[o.ids[o.with_depth][inl]]
                Q = o.points[inl]
                T_kf_cur = invert(o.kf.T_world_keyframe) @ T
                W = information(
                    cov_P, point_information(Q, self.K, self.cfg.depth), T_kf_cur[:3, :3]
                )
                weights = robust_weights(mahalanobis(P, Q, W, T_kf_cur), self.cfg.solver, True)
                eq = sparse_equations(P, Q, W, T_kf_cur, weights)[0]
                A = adjoint(invert(o.kf.T_world_keyframe))
                H += A.T @ eq.H @ A
                g += A.T @ eq.g
            xi = np.linalg.lstsq(H, -g, rcond=None)[0]
            T = orthonormalize(exp_se3(xi) @ T)
            xi_total += xi
            if np.linalg.norm(xi) < self.cfg.solver.convergence_step:
                break
        return T

    def _relocalise(
        self,
        grey: GreyImage,
        depth: Float32Array,
        T_world_pred: FloatArray,
        T_world_prior: FloatArray | None = None,
    ) -> _Registration | None:
        """After a loss: with a prior, its guess against the keyframes nearest to it first; then
        the held pose against the recent keyframes of this segment, newest first (only the
        current one when place recognition follows: it finds the others for less)."""
        if T_world_prior is not None:
            near = sorted(
                self.recent, key=lambda k: pose_distance(k.T_world_keyframe, T_world_prior)
            )
            for kf in near:
                found = self._track_keyframe(kf, grey, depth, T_world_prior, chained=False)
                if found is not None and self._judge(found.solution) is TrackingState.OK:
                    log.info("recovered against keyframe %d from the device pose", kf.id)
                    found.guess_from_prior = True
                    return found
        held = [k for k in reversed(self.recent) if k.segment == self.segment]
        if self.cfg.relocalise.enabled:
            held = [k for k in held if k is self.keyframe]
        for kf in held:
            found = self._track_keyframe(kf, grey, depth, T_world_pred, chained=False)
            if found is not None and self._judge(found.solution) is TrackingState.OK:
                log.info("recovered against keyframe %d", kf.id)
                return found
        return None

    def _recover(
        self, grey: GreyImage, depth: Float32Array
    ) -> _Registration | Relocalisation | None:
        """Place recognition for a frame flow could not register (relocalise config): the
        current keyframe, then the keyframes of the map (and of this segment) the database votes
        for; a verified place is the guess from which flow registers the frame: with the corners
        as last seen (just lost), else against that keyframe when it is held (recent, a saved
        map's or archived). Returns that registration; the place alone when flow cannot follow
        this far (a wide baseline, or a keyframe no longer held: ``_restart_at_place`` goes on
        from it); None when nothing verifies."""
        if not self.cfg.relocalise.enabled or len(self.relocaliser) == 0:
            return None
        query = self._describe(grey, depth)
        current = None if self.keyframe is None else self.keyframe.id
        place = self.relocaliser.find(query, self.T_world_last, {0, self.segment}, current)
        if place is None:
            return None
        segment = self.relocaliser.segment_of[place.keyframe_id]
        found = None
        if self.tracks is not None and self.keyframe is not None and segment == self.segment:
            # Lost just now: the corners as last seen, searched for around the place's pose,
            # span less than a keyframe's corners would.
            found = self._track_keyframe(self.keyframe, grey, depth, place.T_world_camera, True)
        if found is None or self._judge(found.solution) is TrackingState.LOST:
            found = self._track_place(place, grey, depth)
        if found is None or self._judge(found.solution) is TrackingState.LOST:
            log.debug("place found (keyframe %d), flow does not follow", place.keyframe_id)
            return place
        if segment != self.segment:
            log.info("back in the map from segment %d (not merged)", self.segment)
        self.segment = segment
        self.relocaliser.restart_sweep()
        log.info(
            "relocalised against keyframe %d (%d place inliers, %.0f ms)",
            place.keyframe_id,
            place.match.inliers,
            place.ms,
        )
        return found

    def _restart_at_place(
        self,
        index: int,
        grey: GreyImage,
        depth: Float32Array,
        timings: dict[str, float],
        place: Relocalisation,
    ) -> TrackResult | None:
        """A verified place that flow could not follow: the pose from its descriptor matches,
        refined by dense ICP against the keyframe's surface when that keyframe is still held,
        and this frame a new keyframe there (WEAK). None when ICP disagrees with the place."""
        segment = self.relocaliser.segment_of[place.keyframe_id]
        T_world_cur = self._place_pose(place, depth)
        if T_world_cur is None:
            return None
        previous, self.segment = self.segment, segment
        result = self._anchor(index, grey, depth, T_world_cur, timings, relocalised=True)
        if result is None:
            self.segment = previous
            return None
        self.relocaliser.restart_sweep()
        log.info(
            "frame %d: relocalised against keyframe %d by place (%d inliers); new keyframe",
            index,
            place.keyframe_id,
            place.match.inliers,
        )
        return result

    def _place_pose(self, place: Relocalisation, depth: Float32Array) -> FloatArray | None:
        """T_world_camera (4x4, metres) of a verified place, refined by point-to-plane ICP
        (coarse, then at the tracker's own distance) against the matched keyframe's surface
        when that keyframe still holds one (the descriptor matches' pose as it is otherwise);
        None when fewer than ``relocalise.min_icp_overlap`` of the frame's points find it."""
        kf = self._held_keyframe(place.keyframe_id)
        surface = None if kf is None else kf.surface(self.K)
        if kf is None or surface is None:
            return place.T_world_camera
        T_kf_guess = invert(kf.T_world_keyframe) @ place.T_world_camera
        T, overlap = align_to_surface(T_kf_guess, surface, depth, self.K, self.cfg)
        if overlap < self.cfg.relocalise.min_icp_overlap:
            log.info("place of keyframe %d refused by ICP (overlap %.2f)", kf.id, overlap)
            return None
        return orthonormalize(kf.T_world_keyframe @ T)

    def _track_place(
        self, place: Relocalisation, grey: GreyImage, depth: Float32Array
    ) -> _Registration | None:
        """Flow from the place's keyframe, when still held, from the place's pose."""
        kf = self._held_keyframe(place.keyframe_id)
        if kf is None:
            return None
        return self._track_keyframe(kf, grey, depth, place.T_world_camera, chained=False)

    def _held_keyframe(self, keyframe_id: int) -> Keyframe | None:
        """The keyframe with this id: a recent one, a saved map's, or one of the archive (the
        older keyframes, kept without their surface); None when it is no longer held."""
        for kf in [self.keyframe, *self.recent, *self.map_keyframes]:
            if kf is not None and kf.id == keyframe_id:
                return kf
        return self.archive.get(keyframe_id)

    def _start_segment(
        self, index: int, grey: GreyImage, depth: Float32Array, timings: dict[str, float]
    ) -> TrackResult | None:
        """Nothing has registered for ``relocalise.reinit_after`` frames: this frame starts a
        new map segment, as its first keyframe, at the pose the motion before the loss carries
        the last good pose to. Its frames are WEAK and not fused until it merges into the map
        (``_merge_segment``); the trajectory stays in one frame meanwhile. None when the frame
        cannot anchor tracking (too little texture or depth)."""
        frames = self.lost_run  # this one included
        T_world_guess = orthonormalize(
            self.T_world_last @ np.linalg.matrix_power(self._velocity_before_loss, frames)
        )
        previous = self.segment
        self.segment = self.segments_started + 1
        result = self._anchor(index, grey, depth, T_world_guess, timings)
        if result is None:
            self.segment = previous
            return None
        self.segments_started, self._segment_start = self.segment, index
        log.info("frame %d: lost %d frames in a row; new segment %d", index, frames, self.segment)
        return result

    def _merge_segment(
        self, grey: GreyImage, depth: Float32Array, T_world_cur: FloatArray
    ) -> tuple[int, FloatArray] | None:
        """Look this frame (tracked in a segment at ``T_world_cur``) up in the map; found (and
        confirmed by flow against a held map keyframe where there is one), the segment's
        keyframes move into the map with it. Returns (segment, T_correction: segment world to
        map world, 4x4) or None."""
        query = self._describe(grey, depth)
        place = self.relocaliser.find(query, T_world_cur, {0})
        if place is None:
            return None
        found = self._track_place(place, grey, depth)
        if found is not None and self._judge(found.solution) is not TrackingState.LOST:
            T_world_map = orthonormalize(found.kf.T_world_keyframe @ found.solution.T)
        else:
            place_pose = self._place_pose(place, depth)
            if place_pose is None:
                return None
            T_world_map = place_pose
        T_correction = orthonormalize(T_world_map @ invert(T_world_cur))
        segment = self.segment
        held_now = [self.keyframe, *self.recent, *self.archive.values()]
        for held in {id(k): k for k in held_now if k is not None}.values():
            if held.segment == segment:
                held.T_world_keyframe = orthonormalize(T_correction @ held.T_world_keyframe)
                held.segment = 0
        self.relocaliser.merge_segment(segment, T_correction)
        self.relocaliser.restart_sweep()
        self.segment = 0
        log.info(
            "segment %d merged into the map against keyframe %d (%.3f m, %.1f deg)",
            segment,
            place.keyframe_id,
            float(np.linalg.norm(T_correction[:3, 3])),
            rotation_angle_deg(T_correction),
        )
        return segment, T_correction

    def _archive(self, kf: Keyframe) -> None:
        """Keep a keyframe that leaves the recent ones for relocalisation: its image and corners
        (~0.4 MB at 640x480), not its surface (several MB); the oldest go past
        ``relocalise.archive_keyframes``."""
        self.archive[kf.id] = replace(kf, dense=None, depth=None)
        while len(self.archive) > self.cfg.relocalise.archive_keyframes:
            del self.archive[next(iter(self.archive))]

    def _refine(
        self, reg: _Registration, dense: DenseModel, depth: Float32Array, grey: GreyImage
    ) -> FloatArray:
        """Dense refinement of T_keyframe_current, with the sparse inliers kept in the cost."""
        kf, solution = reg.kf, reg.solution
        inl = solution.inliers
        d_ids = reg.ids[reg.with_depth][inl]
        P_in, Q_in = kf.points[d_ids], reg.points[inl]
        cov_Q = point_information(Q_in, self.K, self.cfg.depth)
        W = information(kf.covariances[d_ids], cov_Q, solution.T[:3, :3])

        def sparse_terms(T: FloatArray) -> NormalEquations:
            weights = robust_weights(mahalanobis(P_in, Q_in, W, T), self.cfg.solver, True)
            return sparse_equations(P_in, Q_in, W, T, weights)[0]

        photometric = self.cfg.solver.photometric_weight > 0
        points, intensity = sample_dense_points(
            depth, self.K, self.cfg.solver.dense_stride, grey if photometric else None
        )
        T, _ = refine_dense(
            solution.T, dense, points, sparse_terms, self.cfg.solver, self.cfg.depth, intensity
        )
        return T

    def _judge(self, solution: SparseSolution) -> TrackingState:
        s = self.cfg.state
        n = int(solution.inliers.sum())
        if (
            n < s.lost_inliers
            or solution.condition < s.min_condition
            or not np.isfinite(solution.rmse)
        ):
            return TrackingState.LOST
        if n < s.ok_inliers or solution.rmse > s.ok_rmse:
            return TrackingState.WEAK
        return TrackingState.OK

    def _resume_from_prior(
        self,
        index: int,
        grey: GreyImage,
        depth: Float32Array,
        timings: dict[str, float],
        prior: FloatArray,
        T_world_prior: FloatArray,
    ) -> TrackResult | None:
        """No keyframe registers this view (a gap in the frames, fast motion, blur), but the
        device still knows where it is: a new keyframe at the prior's pose lets tracking go on in
        the map. The device's drift since the last tracked frame (millimetres over a short gap)
        enters the map with it; staying lost until the user comes back to a mapped view would
        lose the rest of the session. The pose is WEAK. None (stay lost) when resuming is off or
        this frame cannot anchor tracking (too little texture or depth)."""
        if not self.cfg.prior.resume_after_loss:
            return None
        if not self.lost:
            log.info("frame %d: no keyframe registers it; resumed from the device pose", index)
        result = self._anchor(index, grey, depth, T_world_prior, timings, prior_used=True)
        if result is not None:
            self.device_last = prior
        return result

    def _anchor(
        self,
        index: int,
        grey: GreyImage,
        depth: Float32Array,
        T_world_camera: FloatArray,
        timings: dict[str, float],
        prior_used: bool = False,
        relocalised: bool = False,
    ) -> TrackResult | None:
        """Make this frame a keyframe at ``T_world_camera`` (4x4, metres; a pose from outside
        flow: the device, a place, the motion model) in the current segment, and go on from it:
        the frame's result is WEAK. None when the frame cannot anchor tracking (too little
        texture or depth)."""
        t = time.perf_counter()
        kf = make_keyframe(
            self.keyframe_count, index, T_world_camera, grey, depth, self.K, self.cfg
        )
        if len(kf.points) < self.cfg.state.ok_inliers:
            return None
        self._adopt_keyframe(kf, grey, depth)
        timings["keyframe"] = _ms(t)
        timings["total"] = sum(v for k, v in timings.items() if k != "total")
        self.velocity = np.eye(4)
        self.T_world_last = T_world_camera.copy()
        self.lost, self.lost_run = False, 0
        return TrackResult(
            index,
            T_world_camera.copy(),
            TrackingState.WEAK,
            len(kf.points),
            0.0,
            1.0,
            kf.id,
            True,
            timings,
            prior_used=prior_used,
            segment=self.segment,
            relocalised=relocalised,
        )

    def _lose(
        self,
        index: int,
        grey: GreyImage,
        timings: dict[str, float],
        inliers: int,
        rmse: float,
        condition: float,
    ) -> TrackResult:
        """Hold the last good pose; keyframes and trajectory stay as they were."""
        if not self.lost:
            log.info("frame %d: tracking lost (%d inliers)", index, inliers)
            self._velocity_before_loss = self.velocity
        self.lost = True
        self.lost_run += 1
        self.velocity = np.eye(4)
        self.tracks = None
        timings["total"] = sum(timings.values())
        kf_id = self.keyframe.id if self.keyframe is not None else -1
        return TrackResult(
            index,
            self.T_world_last.copy(),
            TrackingState.LOST,
            inliers,
            rmse,
            condition,
            kf_id,
            False,
            timings,
            segment=self.segment,
        )

    def _needs_keyframe(self, kf: Keyframe, T_kf_cur: FloatArray, tracked: int) -> bool:
        c = self.cfg.keyframes
        return (
            tracked < max(c.min_tracked, c.min_tracked_ratio * len(kf.points))
            or float(np.linalg.norm(T_kf_cur[:3, 3])) > c.max_translation_m
            or rotation_angle_deg(T_kf_cur) > c.max_rotation_deg
        )

    def _switch_keyframe(
        self, grey: GreyImage, depth: Float32Array, T_world_cur: FloatArray
    ) -> Keyframe | None:
        """Go back to an earlier keyframe that sees this view well, instead of making a new one:
        every new keyframe adds its own error to the chain, an old one adds none. Returns the
        keyframe switched to, or None."""
        c = self.cfg.keyframes
        recent = [k for k in self.recent if k.segment == self.segment]
        candidates = recent + [
            k
            for k in self.map_keyframes
            if k.segment == self.segment and all(k is not r for r in recent)
        ]
        near = sorted(candidates, key=lambda k: pose_distance(k.T_world_keyframe, T_world_cur))
        if c.switch_order == "oldest":
            near.sort(key=lambda k: k.id)
        for kf in near:
            if kf is self.keyframe:
                continue
            T_kf_cur = invert(kf.T_world_keyframe) @ T_world_cur
            if np.linalg.norm(T_kf_cur[:3, 3]) > c.switch_reach * c.max_translation_m:
                if c.switch_order == "nearest":
                    break
                continue
            if rotation_angle_deg(T_kf_cur) > c.switch_reach * c.max_rotation_deg:
                continue
            reg = self._track_keyframe(kf, grey, depth, T_world_cur, chained=False)
            if reg is None or self._judge(reg.solution) is not TrackingState.OK:
                continue
            keep = reg.surviving()
            need = c.switch_tracked_factor * c.min_tracked_ratio * len(kf.points)
            if keep.sum() < max(c.min_tracked, need):
                continue
            self.keyframe = kf
            self.tracks = _Tracks(reg.ids[keep], reg.uv[keep], grey)
            return kf
        return None

    def _new_keyframe(
        self, index: int, grey: GreyImage, depth: Float32Array, T_world_camera: FloatArray
    ) -> Keyframe:
        kf = make_keyframe(
            self.keyframe_count, index, T_world_camera, grey, depth, self.K, self.cfg
        )
        self._adopt_keyframe(kf, grey, depth)
        return kf

    def _adopt_keyframe(self, kf: Keyframe, grey: GreyImage, depth: Float32Array) -> None:
        """Make kf the keyframe the next frames track against, in the current segment, and
        describe it for place recognition (depth: cleaned, metres)."""
        self.keyframe_count += 1
        kf.segment = self.segment
        self.keyframe = kf
        if len(self.recent) == self.recent.maxlen and self.cfg.relocalise.enabled:
            self._archive(self.recent[0])
        self.recent.append(kf)
        self.tracks = _Tracks(np.arange(len(kf.uv)), kf.uv.copy(), grey)
        if self.cfg.relocalise.enabled:
            features = self._describe(grey, depth)
            self.relocaliser.add(kf.id, self.segment, kf.T_world_keyframe, features)

    def _describe(self, grey: GreyImage, depth: Float32Array) -> PlaceFeatures:
        """A frame's place features (its grey image and cleaned depth, metres), described once
        however many steps of recovery and keyframing ask for them."""
        if self._described is None or self._described[0] is not grey:
            self._described = (grey, self.relocaliser.describe(grey, depth))
        return self._described[1]


def _quality(solution: SparseSolution) -> tuple[int, float, float]:
    """(inliers, rmse, condition) of a sparse solution, as a TrackResult reports them."""
    return int(solution.inliers.sum()), solution.rmse, solution.condition


def _ms(t0: float) -> float:
    return (time.perf_counter() - t0) * 1e3
