"""The per-frame registration pipeline: track corners, solve the pose, refine, manage keyframes.

Read ``Tracker.track`` top to bottom: it follows the paper's section III with the additions that
make it hold up on real hand-held data (keyframes, robust weights, a tracking state, recovery).
Each stage is its own module: the device's prior (``prior``), registration against a keyframe
(``frame_to_keyframe``), the keyframes and their changes (``keyframes``), recovery after a loss
(``recovery``). The state that passes from frame to frame, and its changes besides a registered
frame (the first frame, a frame made a keyframe at a pose from elsewhere, a lost frame, a saved
map, a corrected world), is the tracker's base, ``TrackerMemory`` (``tracker_memory``).

A frame is registered in two phases, so that a live session can publish the pose before the
slower keyframe work: :meth:`Tracker.track` returns the pose and says whether a keyframe change
is due; :meth:`Tracker.update_keyframe` then switches to an old keyframe or builds a new one.
"""

from __future__ import annotations

import time
from functools import partial

import numpy as np

from server.geometry import invert, orthonormalize
from server.geometry.arrays import Float32Array, FloatArray, GreyImage
from server.registration.frame_to_keyframe import (
    Registration,
    Tracks,
    judge,
    quality,
    refine_on_surface,
    track_keyframe,
)
from server.registration.keyframe import Keyframe
from server.registration.keyframes import PendingKeyframe, needs_keyframe, refine_in_window
from server.registration.preprocess import clean_depth, to_grey
from server.registration.relocalise import Relocalisation
from server.registration.results import TrackingState, TrackResult
from server.registration.tracker_memory import TrackerMemory, elapsed_ms

__all__ = ["Tracker", "TrackingState", "TrackResult"]


class Tracker(TrackerMemory):
    """Frame-to-keyframe RGB-D odometry (FAST + pyramidal LK + Gauss-Newton on SE(3)).

    Feed frames in order to :meth:`track`; poses are T_world_camera with the first frame at
    ``T_world_first`` (identity by default). The world is the map. Call :meth:`update_keyframe`
    after each ``track`` (once the pose is sent): otherwise the next ``track`` does it first,
    which gives the same trajectory but leaves the earlier result's ``new_keyframe`` unknown to
    its caller. A frame may carry the device's own pose as a prior (see ``track``);
    ``T_world_device`` then says where the device's world lies in the map. The constructor,
    the state and the moves into a saved map (``resume_in_map``) or a corrected world
    (``apply_correction``) are ``TrackerMemory``'s.
    """

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
            timings = {"preprocess": elapsed_ms(t0)}
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
        timings = {"preprocess": elapsed_ms(t0)}

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
        timings["sparse"] = elapsed_ms(t)
        state = None if found is None else self._judge(found)
        relocalised = False
        # 3b-3d. Flow found nothing: recovery makes the frame a keyframe where it places it.
        anchor = partial(self._anchor, index, grey, depth, timings)
        if state in (None, TrackingState.LOST):
            # 3b. Look the frame up among every keyframe, in this frame.
            t = time.perf_counter()
            recovered = self.recovery.recover(grey, depth, self.tracks, self.T_world_last)
            timings["relocalise"] = elapsed_ms(t)
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
            timings["dense"] = elapsed_ms(t)

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
            timings["merge"] = elapsed_ms(t)
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
        timings["total"] = elapsed_ms(t0)
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
            c = self.cfg.keyframes
            window = min(c.window, c.window_when_behind) if self.recovery.behind else c.window
            if window > 0 and p.registration is not None:
                T_world_kf = refine_in_window(
                    self.recent,
                    p.grey,
                    p.depth,
                    T_world_kf,
                    p.registration,
                    self.K,
                    self.cfg,
                    window,
                )
                self.T_world_last = T_world_kf
            kf = self._new_keyframe(p.index, p.grey, p.depth, T_world_kf)
        ms = elapsed_ms(t)
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
