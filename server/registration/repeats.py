"""Repeated frames: a source that sends one image again while the other moved on (a phone's
depth at a lower rate than its colour) would pair images of two moments. Such a frame is not
tracked but held at the last tracked frame's pose (``state.hold_repeated_frames``)."""

from __future__ import annotations

import numpy as np

from server.geometry.arrays import Float32Array, FloatArray, GreyImage
from server.registration.results import TrackResult


class Repeats:
    """Tells a frame whose images repeat the previous frame's, and holds it.

    ``last``: the last frame's result that was not held; ``held``: frames held since then.
    """

    def __init__(self) -> None:
        self._previous: tuple[GreyImage, Float32Array] | None = None
        self.last: TrackResult | None = None
        self.held = 0

    def check(self, grey: GreyImage, depth: Float32Array) -> str | None:
        """Which of this frame's images (grey, and depth as given) are the very same as the
        previous frame's: "colour", "depth", "both" or None."""
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

    def hold(
        self,
        index: int,
        repeated: str,
        timings: dict[str, float],
        T_world_camera: FloatArray,
        prior_used: bool,
        keyframe_id: int | None,
        segment: int,
    ) -> TrackResult:
        """Frame ``index``'s result, a held repeat: the last result's state at T_world_camera
        (4x4, metres: the last tracked pose, or moved by the device's own motion since then when
        ``prior_used``); ``keyframe_id``: the current keyframe (None: the last result's)."""
        last = self.last
        assert last is not None
        timings["total"] = sum(timings.values())
        return TrackResult(
            index,
            T_world_camera,
            last.state,
            last.inliers,
            last.rmse,
            last.condition,
            last.keyframe_id if keyframe_id is None else keyframe_id,
            False,
            timings,
            prior_used=prior_used,
            repeated=repeated,
            segment=segment,
        )
