"""The per-frame registration pipeline: track corners, solve the pose, refine, manage keyframes.

Read ``Tracker.track`` top to bottom: it follows the paper's section III with the additions that
make it hold up on real hand-held data (keyframes, robust weights, a tracking state, recovery).
Each stage is its own module: the device's prior (``prior``), registration against a keyframe
(``frame_to_keyframe``), the keyframes and their changes (``keyframes``), recovery after a loss
(``recovery``); the tracker holds the state that passes from frame to frame.

A frame is registered in two phases, so that a live session can publish the pose before the
slower keyframe work: :meth:`Tracker.track` returns the pose and says whether a keyframe change
is due; :meth:`Tracker.update_keyframe` then switches to an old keyframe or builds a new one.
"""

from __future__ import annotations

import logging
import time
from collections import deque
from functools import partial

import numpy as np

from server.geometry import Intrinsics, invert, orthonormalize
from server.geometry.arrays import Float32Array, FloatArray, GreyImage
from server.registration.config import RegistrationConfig
from server.registration.frame_to_keyframe import (
    Registration,
    Tracks,
    judge,
    quality,
    refine_on_surface,
    track_keyframe,
)
from server.registration.keyframe import Keyframe
from server.registration.keyframes import (
    Keyframes,
    PendingKeyframe,
    needs_keyframe,
    refine_in_window,
)
from server.registration.place import KeyframeDatabase
from server.registration.preprocess import clean_depth, to_grey
from server.registration.prior import DevicePrior
from server.registration.recovery import Recovery
from server.registration.relocalise import Relocalisation
from server.registration.repeats import Repeats
from server.registration.results import TrackingState, TrackResult

__all__ = ["Tracker", "TrackingState", "TrackResult"]

log = logging.getLogger(__name__)


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
        self.keyframes = Keyframes(intrinsics, self.cfg)
        self.tracks: Tracks | None = None
        self.T_world_last: FloatArray = self.T_world_first.copy()
        self.velocity: FloatArray = np.eye(4)  # T_previous_last: motion over the last frame
        self.lost = False
        self.frame_count = 0
        self.pending: PendingKeyframe | None = None
        self.device = DevicePrior(self.cfg.prior)
        self.repeats = Repeats()  # repeated frames held, and the last result not held
        self.recovery = Recovery(intrinsics, self.cfg, self.keyframes)

    @property
    def keyframe(self) -> Keyframe | None:
        """The keyframe the next frame is tracked against (None before the first)."""
        return self.keyframes.current

    @property
    def recent(self) -> deque[Keyframe]:
        """The recent keyframes, newest last."""
        return self.keyframes.recent

    @property
    def keyframe_count(self) -> int:
        """Keyframes made so far (and a saved map's): the next keyframe's id."""
        return self.keyframes.count

    @property
    def T_world_device(self) -> FloatArray | None:
        """The device's world frame in the map (4x4, metres), once a frame with a prior tracked
        ok; None before. Maps a device-world point into the map: p_world = T @ p_device."""
        T = self.device.alignment.T_world_device
        return None if T is None else T.copy()

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
        self.keyframes.resume(keyframe, map_keyframes)
        self.recovery.reset(places)
        self.tracks = None
        self.pending = None
        self.T_world_last = orthonormalize(np.asarray(T_world_camera, dtype=np.float64))
        self.velocity = np.eye(4)
        self.repeats.held = 0
        self.lost = False
        self.device.reset()

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
        self.recovery.correct(keyframe_poses, T_correction)
        self.T_world_last = orthonormalize(T_correction @ self.T_world_last)
        self.T_world_first = orthonormalize(T_correction @ self.T_world_first)
        if self.pending is not None:  # a keyframe change found due and not yet made
            self.pending.T_world_camera = orthonormalize(T_correction @ self.pending.T_world_camera)
        self.device.alignment.reset()

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
        prior = self.device.check(T_device_camera)
        self.device.enter_world(device_world)
        repeated = self.repeats.check(grey, depth) if self.cfg.state.hold_repeated_frames else None
        if repeated is not None and self.repeats.last is not None and not self.lost:
            # Not tracked: held at the last tracked pose, or where the device says it moved
            # since (its camera did move, and AR draws on this frame).
            timings = {"preprocess": _ms(t0)}
            self.repeats.held += 1
            T_prior = self.device.guess(prior, self.T_world_last)
            T_world = self.T_world_last.copy() if T_prior is None else T_prior
            kf_id = None if self.keyframe is None else self.keyframe.id
            segment = self.recovery.segment
            return self.repeats.hold(
                index, repeated, timings, T_world, T_prior is not None, kf_id, segment
            )
        self.repeats.last = self._register(index, grey, depth, prior, t0)
        return self.repeats.last

    def _register(
        self,
        index: int,
        grey: GreyImage,
        depth: Float32Array,
        prior: FloatArray | None,
        t0: float,
    ) -> TrackResult:
        """Steps 1-6 for a frame that is not a held repeat (``track``): depth as given, metres."""
        depth = clean_depth(depth, self.cfg.depth)
        timings = {"preprocess": _ms(t0)}

        if self.keyframe is None:
            return self._start(index, grey, depth, timings, prior)

        # 1. Predict the pose: by the device's own motion when it sends one, else with a
        # constant-velocity model (also the fallback when the prior's guess fails), over the
        # frames held since the last tracked one too.
        gap, self.repeats.held = 1 + self.repeats.held, 0
        T_world_pred = orthonormalize(
            self.T_world_last @ np.linalg.matrix_power(self.velocity, gap)
        )
        T_world_prior = self.device.guess(prior, self.T_world_last)

        # 2-3. Track corners (from the previous frame, or from keyframes after a loss), solve.
        t = time.perf_counter()
        if self.lost:
            found = self.recovery.retrack(grey, depth, T_world_pred, T_world_prior)
        else:
            found = None
            if T_world_prior is not None:
                found = self._track_keyframe(self.keyframe, grey, depth, T_world_prior)
                if found is None or self._judge(found) is TrackingState.LOST:
                    found = None  # a wrong prior: try the guess without it
                else:
                    found.guess_from_prior = True
            if found is None:
                found = self._track_keyframe(self.keyframe, grey, depth, T_world_pred)
        timings["sparse"] = _ms(t)
        state = None if found is None else self._judge(found)
        relocalised = False
        # 3b-3d. Flow found nothing: recovery makes the frame a keyframe where it places it.
        anchor = partial(self._anchor, index, grey, depth, timings)
        if state in (None, TrackingState.LOST):
            # 3b. Look the frame up among every keyframe, in this frame.
            t = time.perf_counter()
            recovered = self.recovery.recover(grey, depth, self.tracks, self.T_world_last)
            timings["relocalise"] = _ms(t)
            if isinstance(recovered, Relocalisation):  # found, but flow cannot follow
                restarted = self.recovery.restart_at_place(recovered, depth, anchor)
                if restarted is not None:
                    return restarted
            elif recovered is not None:
                found, state, relocalised = recovered, self._judge(recovered), True
        if state in (None, TrackingState.LOST) and prior is not None and T_world_prior is not None:
            # 3c. Not found in the map either: the device's pose carries tracking on (its drift
            # over the gap enters the map, so it comes after place recognition).
            resumed = self.device.resume(index, prior, T_world_prior, anchor, self.lost)
            if resumed is not None:
                return resumed
        if found is None or state is None or state is TrackingState.LOST:
            # 3d. Lost: the last good pose is held; after a few such frames, a new segment.
            n, rmse, cond = (0, np.inf, 0.0) if found is None else quality(found.solution)
            lost = self._lose(index, timings, n, rmse, cond)
            started = self.recovery.start_segment(self.T_world_last, anchor)
            return lost if started is None else started
        kf, solution = found.kf, found.solution

        # 4. Dense refinement from the sparse estimate.
        T_kf_cur = solution.T
        if self.cfg.solver.dense and kf.dense is not None:
            t = time.perf_counter()
            T_kf_cur = refine_on_surface(found, kf.dense, depth, grey, self.K, self.cfg)
            timings["dense"] = _ms(t)

        # 5. Accept the pose, keep the surviving tracks, and note whether a keyframe change is due.
        T_world_cur = orthonormalize(kf.T_world_keyframe @ T_kf_cur)
        if self.lost or relocalised:
            self.velocity = np.eye(4)
        elif gap == 1:  # after held frames the motion spans several frames: keep the old one
            self.velocity = invert(self.T_world_last) @ T_world_cur
        self.lost, self.recovery.lost_run = False, 0
        # 6. In a segment: now and then, look for the map; found, the segment moves into it.
        merged = None
        if self.recovery.merge_due(index):
            t = time.perf_counter()
            merged = self.recovery.merge(grey, depth, T_world_cur)
            timings["merge"] = _ms(t)
            if merged is not None:
                T_world_cur = orthonormalize(merged[1] @ T_world_cur)
        self.T_world_last = T_world_cur
        if self.recovery.segment != 0 and state is TrackingState.OK:
            state = TrackingState.WEAK  # tracked, but where the segment lies is a guess
        self.keyframes.current = kf
        self.device.tracked(prior, T_world_cur, state is TrackingState.OK)
        keep = found.surviving()
        self.tracks = Tracks(found.ids[keep], found.uv[keep], grey)
        due = needs_keyframe(kf, T_kf_cur, len(self.tracks.ids), self.cfg.keyframes)
        timings["total"] = _ms(t0)
        result = TrackResult(
            index,
            T_world_cur.copy(),
            state,
            *quality(solution),
            kf.id,
            False,
            timings,
            keyframe_due=due,
            prior_used=found.guess_from_prior,
            segment=self.recovery.segment,
            merged=merged,
            relocalised=relocalised,
        )
        if due:
            self.pending = PendingKeyframe(index, grey, depth, T_world_cur, result, found)
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
        switched = self.keyframes.switch(self.recovery.segment, p)
        if switched is not None:
            kf, self.tracks = switched
        else:
            T_world_kf = p.T_world_camera
            if self.cfg.keyframes.window > 0 and p.registration is not None:
                T_world_kf = refine_in_window(
                    self.recent, p.grey, p.depth, T_world_kf, p.registration, self.K, self.cfg
                )
                self.T_world_last = T_world_kf
            kf = self._new_keyframe(p.index, p.grey, p.depth, T_world_kf)
        ms = _ms(t)
        r = p.result
        r.new_keyframe, r.keyframe_id, r.keyframe_due = switched is None, kf.id, False
        r.timings_ms["keyframe"] = ms
        r.timings_ms["total"] = r.timings_ms.get("total", 0.0) + ms
        return switched is None

    # ------------------------------------------------------------------ stages
    def _track_keyframe(
        self, kf: Keyframe, grey: GreyImage, depth: Float32Array, T_world_pred: FloatArray
    ) -> Registration | None:
        """Registration against ``kf`` with the corners followed from the previous frame."""
        return track_keyframe(kf, grey, depth, T_world_pred, self.K, self.cfg, self.tracks)

    def _judge(self, found: Registration) -> TrackingState:
        return judge(found.solution, self.cfg.state)

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
            self.keyframes.current, self.lost = None, True
            self.keyframes.recent.clear()
            self.recovery.reset()
        else:
            self.device.tracked(prior, self.T_world_first, ok=True)
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

    def _anchor(
        self,
        index: int,
        grey: GreyImage,
        depth: Float32Array,
        timings: dict[str, float],
        T_world_camera: FloatArray,
        segment: int | None = None,
        *,
        prior_used: bool = False,
        relocalised: bool = False,
    ) -> TrackResult | None:
        """Make this frame a keyframe at ``T_world_camera`` and go on from it (see ``Anchor``:
        grey image, cleaned depth in metres, and the frame's timings so far bound first)."""
        t = time.perf_counter()
        kf = self.keyframes.make(index, T_world_camera, grey, depth)
        if len(kf.points) < self.cfg.state.ok_inliers:
            return None
        if segment is not None:
            self.recovery.segment = segment
        self._adopt_keyframe(kf, grey, depth)
        timings["keyframe"] = _ms(t)
        timings["total"] = sum(v for k, v in timings.items() if k != "total")
        self.velocity = np.eye(4)
        self.T_world_last = T_world_camera.copy()
        self.lost, self.recovery.lost_run = False, 0
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
            segment=self.recovery.segment,
            relocalised=relocalised,
        )

    def _lose(
        self, index: int, timings: dict[str, float], inliers: int, rmse: float, condition: float
    ) -> TrackResult:
        """Hold the last good pose; keyframes and trajectory stay as they were."""
        if not self.lost:
            log.info("frame %d: tracking lost (%d inliers)", index, inliers)
        self.recovery.lose(self.velocity, first=not self.lost)
        self.lost = True
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
            segment=self.recovery.segment,
        )

    def _new_keyframe(
        self, index: int, grey: GreyImage, depth: Float32Array, T_world_camera: FloatArray
    ) -> Keyframe:
        kf = self.keyframes.make(index, T_world_camera, grey, depth)
        self._adopt_keyframe(kf, grey, depth)
        return kf

    def _adopt_keyframe(self, kf: Keyframe, grey: GreyImage, depth: Float32Array) -> None:
        """Make kf the keyframe the next frames track against, in the current segment, and
        describe it for place recognition (depth: cleaned, metres)."""
        left = self.keyframes.add(kf, self.recovery.segment)
        if left is not None and self.cfg.relocalise.enabled:
            self.recovery.archive_keyframe(left)
        self.tracks = Tracks(np.arange(len(kf.uv)), kf.uv.copy(), grey)
        if self.cfg.relocalise.enabled:
            self.recovery.add_keyframe(kf, grey, depth)


def _ms(t0: float) -> float:
    return (time.perf_counter() - t0) * 1e3
