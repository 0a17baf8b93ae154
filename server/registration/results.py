"""What registering one frame gives: its pose, how far to trust it, and how it was found."""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum
from typing import Protocol

from server.geometry.arrays import FloatArray


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


class Anchor(Protocol):
    """Makes the frame being registered a keyframe at ``T_world_camera`` (4x4, metres; a pose
    from outside flow: a place, the motion model, the device) in map segment ``segment`` (None:
    the current one) and goes on from it (``Tracker._anchor``): the frame's result, WEAK, or None
    when the frame cannot anchor tracking (too little texture or depth)."""

    def __call__(
        self,
        T_world_camera: FloatArray,
        segment: int | None = None,
        *,
        prior_used: bool = False,
        relocalised: bool = False,
    ) -> TrackResult | None: ...
