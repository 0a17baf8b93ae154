"""Which of the blocks a frame touches are worth fusing: a block that many frames have fused
already has settled, and one more observation moves its running average by 1/(weight + 1) at
most (Open3D's TSDF weight grows without a cap). Fusing it costs as much as fusing a new one
(every voxel of the block, server/mapping/tsdf.py), so a settled block is fused on every n-th
frame that touches it only. Where the camera looks at a mapped room (a pilot flying, a second
pass, a phone that joined late), most blocks in view have settled and fusion costs a fraction;
where it sees new space, nothing changes.

A block still takes observations, less often: a moved chair still fades out of the map and
into its new place, over n times as many frames.
"""

from __future__ import annotations

import numpy as np

from server.geometry.arrays import Int64Array


class SettledBlocks:
    """How many frames have touched each block (packed keys, ``occupancy.pack_keys``) since
    this map started. after: touches that settle a block (0: never, every block is always
    fused); every: a settled block is fused on every ``every``-th touch."""

    def __init__(self, after: int, every: int) -> None:
        if after < 0 or every < 1:
            raise ValueError(f"settled blocks need after >= 0 and every >= 1, got {after}, {every}")
        self.after = after
        self.every = every
        self._keys = np.empty(0, np.int64)  # sorted
        self._touches = np.empty(0, np.int64)
        self.skipped = 0  # block fusions left out so far (for tests and benchmarks)

    def to_fuse(self, keys: Int64Array) -> Int64Array:
        """Of ``keys`` (unique, sorted: the blocks one frame touches) those to fuse; counts the
        touch of every one of them."""
        if self.after == 0 or keys.size == 0:
            return keys
        pos = np.searchsorted(self._keys, keys)
        known = pos < self._keys.size
        known[known] = self._keys[pos[known]] == keys[known]
        touches = np.zeros(keys.size, np.int64)
        touches[known] = self._touches[pos[known]]
        settled = touches >= self.after
        fuse = ~settled | ((touches - self.after) % self.every == self.every - 1)
        self._touches[pos[known]] += 1
        if not known.all():
            fresh = keys[~known]
            merged = np.concatenate([self._keys, fresh])
            order = np.argsort(merged, kind="stable")
            self._keys = merged[order]
            self._touches = np.concatenate([self._touches, np.ones(fresh.size, np.int64)])[order]
        self.skipped += int(keys.size - fuse.sum())
        kept: Int64Array = keys[fuse]
        return kept
