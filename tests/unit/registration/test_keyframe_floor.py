"""When a keyframe change is due: the floor of corners still followed scales with the image."""

from __future__ import annotations

import numpy as np

from server.registration.config import KeyframeConfig
from server.registration.keyframe import Keyframe
from server.registration.keyframes import min_tracked, needs_keyframe


def keyframe(width: int, height: int, corners: int) -> Keyframe:
    return Keyframe(
        id=0,
        frame_index=0,
        T_world_keyframe=np.eye(4),
        grey=np.zeros((height, width), np.uint8),
        uv=np.zeros((corners, 2), np.float32),
        points=np.tile([0.0, 0.0, 1.5], (corners, 1)),
        covariances=np.tile(np.eye(3) * 1e-4, (corners, 1, 1)),
        dense=None,
    )


def test_a_640x480_keyframe_keeps_the_configured_floor():
    c = KeyframeConfig()
    assert min_tracked(keyframe(640, 480, 170), c) == c.min_tracked
    assert min_tracked(keyframe(1280, 960, 170), c) == c.min_tracked  # never above it


def test_a_phones_narrow_view_is_not_rekeyed_after_losing_a_few_corners():
    """A 640x288 live AR keyframe holds about 89 corners: with the 640x480 floor (80) a frame
    that still follows 70 of them (79 %) would need a new keyframe; the floor of its size (62)
    does not. Below that floor, or below half of its corners, the change is still due."""
    c = KeyframeConfig()
    still = np.eye(4)
    phone, vga = keyframe(640, 288, 89), keyframe(640, 480, 89)
    assert round(min_tracked(phone, c)) == 62
    assert needs_keyframe(vga, still, 70, c)
    assert not needs_keyframe(phone, still, 70, c)
    assert needs_keyframe(phone, still, 61, c)
    big = keyframe(640, 288, 200)
    assert needs_keyframe(big, still, 99, c) and not needs_keyframe(big, still, 100, c)
