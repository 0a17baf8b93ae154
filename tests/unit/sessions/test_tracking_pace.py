"""The tracking thread tells the tracker when the session is behind: a frame dropped for a
newer one makes the next BEHIND_FRAMES frames count as behind (``SessionTracking._pace``)."""

from __future__ import annotations

import logging

from server.sessions.runtime.counts import SessionCounts
from server.sessions.runtime.tracking import BEHIND_FRAMES, SessionTracking


class _Step:
    """What the tracking thread tells the frame step, frame by frame."""

    def __init__(self) -> None:
        self.paced: list[bool] = []

    def pace(self, behind: bool) -> None:
        self.paced.append(behind)


def test_a_dropped_frame_makes_the_next_frames_count_as_behind():
    counts, step = SessionCounts(), _Step()
    tracking = SessionTracking(
        step,  # type: ignore[arg-type]
        None,  # type: ignore[arg-type]
        counts,
        lambda update: None,
        logging.LoggerAdapter(logging.getLogger("test"), {}),
        "tracking",
        None,
        lambda seq, exc: None,
        dict,
    )
    for _ in range(3):
        tracking._pace()
    assert step.paced == [False] * 3
    with counts.lock:
        counts.dropped += 1
    for _ in range(BEHIND_FRAMES + 2):
        tracking._pace()
    assert step.paced[3:] == [True] * BEHIND_FRAMES + [False] * 2
    # Another drop while behind starts the count again.
    step.paced.clear()
    with counts.lock:
        counts.dropped += 2
    tracking._pace()
    with counts.lock:
        counts.dropped += 1
    for _ in range(BEHIND_FRAMES):
        tracking._pace()
    assert step.paced == [True] * (BEHIND_FRAMES + 1)
    tracking._pace()
    assert step.paced[-1] is False
