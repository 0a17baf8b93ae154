"""Offline stages overlapped with tracking (server/overlap.py): frames read ahead and map work
done behind keep their order, pass errors on where they belong, and ``run_odometry`` gives the
same trajectory, map and room with them as with every stage in turn."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from server.datasets import open_dataset
from server.errors import DatasetError
from server.overlap import Behind, read_ahead
from server.pipeline import run_odometry
from server.rooms import load_room, save_room

pytestmark = pytest.mark.slow  # unit, not in the fast tier (tests/conftest.py)


def _threads(name: str) -> int:
    return sum(t.name == name and t.is_alive() for t in threading.enumerate())


def test_read_ahead_keeps_the_order_and_raises_where_the_failing_item_was():
    def items():
        for i in range(10):
            if i == 6:
                raise ValueError("frame 6 is broken")
            time.sleep(0.001 * (i % 3))
            yield i

    got = []
    with pytest.raises(ValueError, match="frame 6"):
        for i in read_ahead(items(), ahead=2):
            got.append(i)
    assert got == [0, 1, 2, 3, 4, 5]
    assert list(read_ahead(range(20), ahead=3, threaded=False)) == list(range(20))


def test_read_ahead_closed_early_stops_its_thread():
    produced = []

    def items():
        for i in range(1000):
            produced.append(i)
            yield i

    gen = read_ahead(items(), ahead=2)
    assert next(gen) == 0
    gen.close()
    deadline = time.time() + 5
    while _threads("read-ahead") and time.time() < deadline:
        time.sleep(0.01)
    assert _threads("read-ahead") == 0
    assert len(produced) < 10  # it stopped, not read all 1000


def test_behind_runs_jobs_in_order_off_the_callers_thread_and_reports_the_first_failure():
    seen: list[tuple[int, str]] = []
    behind = Behind(limit=2, name="test-behind")
    for i in range(8):
        behind.submit(lambda k: seen.append((k, threading.current_thread().name)), i)
    behind.join()
    assert [k for k, _ in seen] == list(range(8))
    assert {name for _, name in seen} == {"test-behind"}

    def fail(k: int) -> None:
        if k == 3:
            raise RuntimeError("job 3 failed")
        seen.append((k, ""))

    seen.clear()
    behind = Behind(limit=2)
    with pytest.raises(RuntimeError, match="job 3"):
        for i in range(8):
            behind.submit(fail, i)
        behind.join()
    assert [k for k, _ in seen] == [0, 1, 2]  # nothing after the failure ran


def test_overlapped_run_equals_the_run_in_turn(shared_data, tmp_path):
    ds = open_dataset(shared_data / "synthetic_room0")
    runs = {
        overlap: run_odometry(ds, max_frames=45, progress=False, overlap=overlap)
        for overlap in (True, False)
    }
    a, b = runs[True], runs[False]
    assert a.room.keyframes and len(a.room.keyframes) == len(b.room.keyframes)
    np.testing.assert_array_equal(a.trajectory.poses, b.trajectory.poses)
    np.testing.assert_array_equal(a.map.points, b.map.points)
    np.testing.assert_array_equal(a.map.colours, b.map.colours)
    for ka, kb in zip(a.room.keyframes, b.room.keyframes, strict=True):
        assert ka.id == kb.id
        np.testing.assert_array_equal(ka.place.descriptors, kb.place.descriptors)
    # The room's map was fused behind tracking; saved and read back, it holds what a map
    # re-fused from the keyframes at save time holds.
    save_room(a.room, tmp_path / "a")
    b.room.map = None
    save_room(b.room, tmp_path / "b")
    pa, _ = load_room(tmp_path / "a").map.point_cloud()
    pb, _ = load_room(tmp_path / "b").map.point_cloud()
    assert len(pa) > 1000
    # The same surface; the grid's hash map may list its blocks in another order.
    np.testing.assert_array_equal(pa[np.lexsort(pa.T)], pb[np.lexsort(pb.T)])


class _Broken:
    """A dataset whose frame ``bad`` cannot be read."""

    def __init__(self, ds, bad: int) -> None:
        self._ds, self._bad = ds, bad

    def __getattr__(self, name):
        return getattr(self._ds, name)

    def __len__(self) -> int:
        return len(self._ds)

    def __getitem__(self, i: int):
        if i == self._bad:
            raise DatasetError(f"frame {i}: the depth file is truncated")
        return self._ds[i]


def test_a_frame_that_cannot_be_read_fails_the_run_and_leaves_no_thread(shared_data):
    ds = _Broken(open_dataset(shared_data / "synthetic_room0"), bad=12)
    with pytest.raises(DatasetError, match="frame 12"):
        run_odometry(ds, max_frames=30, progress=False)
    deadline = time.time() + 5
    while (_threads("read-ahead") or _threads("map")) and time.time() < deadline:
        time.sleep(0.01)
    assert _threads("read-ahead") == 0 and _threads("map") == 0
