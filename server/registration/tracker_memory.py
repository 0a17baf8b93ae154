"""What the tracker carries from one frame to the next, and every change to it that is not a
frame registered by flow.

``TrackerMemory`` holds the last pose and motion, the corners followed, the keyframes, the device
prior, the held repeats and the recovery (``TrackingState`` is one frame's verdict,
ok / weak / lost). Besides the per-frame registration (``Tracker``, server/registration/tracker.py,
which builds on it), the state changes here: the first frame starts it (``_start``); a frame made
a keyframe at a pose from outside flow restarts it (``_anchor``: a place, the motion model, the
device); a lost frame holds the last pose (``_lose``); a new keyframe is adopted; a saved map or
a corrected world (loop closure) moves it between frames.
"""

from __future__ import annotations

import logging
import time
from collections import deque

import numpy as np

from server.geometry import Intrinsics, orthonormalize
from server.geometry.arrays import Float32Array, FloatArray, GreyImage
from server.registration.config import RegistrationConfig
from server.registration.frame_to_keyframe import Tracks
from server.registration.keyframe import Keyframe
from server.registration.keyframes import Keyframes, PendingKeyframe
from server.registration.place import KeyframeDatabase
from server.registration.prior import DevicePrior
from server.registration.recovery import Recovery
from server.registration.repeats import Repeats
from server.registration.results import TrackingState, TrackResult

log = logging.getLogger(__name__)


class TrackerMemory:
    """The tracker's state between frames, and its changes besides a registered frame (see the
    module's docstring); ``Tracker`` registers the frames. Poses are T_world_camera (4x4, metres)
    with the first frame at ``T_world_first`` (identity by default)."""

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

    def pace(self, behind: bool) -> None:
        """Whether the caller is behind (dropping frames): a new keyframe is then not refined
        against the window of recent ones (``keyframes.window_when_behind``), and a map segment
        looks for the map less often (``relocalise.merge_every_behind``)."""
        self.recovery.behind = behind

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

    # ------------------------------------------------------------------ state changes
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
        timings["keyframe"] = elapsed_ms(t)
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
        timings["keyframe"] = elapsed_ms(t)
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


def elapsed_ms(t0: float) -> float:
    """Milliseconds since ``t0`` (a ``time.perf_counter()`` reading)."""
    return (time.perf_counter() - t0) * 1e3
