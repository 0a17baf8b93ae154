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


def test_a_keyframe_change_registers_at_most_switch_tries_earlier_keyframes(monkeypatch):
    """Each try to go back to an earlier keyframe is a whole registration; past the nearest
    they failed on a phone's view (7scenes_a at 640x288: 105 tries in 41 changes, none kept),
    so a change tries ``switch_tries`` of them, nearest first."""
    from dataclasses import replace

    from server.geometry import Intrinsics
    from server.registration import keyframes as kf_module
    from server.registration.config import RegistrationConfig

    tried: list[int] = []
    monkeypatch.setattr(kf_module, "track_keyframe", lambda kf, *args: tried.append(kf.id) or None)
    earlier = []
    for i in range(1, 5):
        kf = keyframe(640, 480, 170)
        kf.id, kf.T_world_keyframe = i, np.eye(4)
        kf.T_world_keyframe[0, 3] = 0.01 * i  # all within reach, nearer the higher the id
        earlier.append(kf)
    current = keyframe(640, 480, 170)
    current.id = 9
    here = np.eye(4)
    here[0, 3] = 0.05
    K = Intrinsics(500.0, 500.0, 320.0, 240.0, 640, 480)
    grey, depth = np.zeros((480, 640), np.uint8), np.ones((480, 640), np.float32)
    for tries, expected in ((1, [4]), (2, [4, 3]), (9, [4, 3, 2, 1])):
        cfg = RegistrationConfig()
        cfg = replace(cfg, keyframes=replace(cfg.keyframes, switch_tries=tries))
        tried.clear()
        args = (grey, depth, here, K, cfg)
        assert kf_module.switch_keyframe(earlier, [], current, 0, *args) is None
        assert tried == expected
