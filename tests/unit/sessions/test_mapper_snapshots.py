"""A session's map snapshots (``Mapper.save``): the periodic ones, crash insurance, cost less
(the npz stored, not deflated; map.ply now and then); the last one is whole and compact."""

from __future__ import annotations

import zipfile

import numpy as np
import open3d as o3d
import pytest

from server.datasets import open_dataset
from server.mapping.config import MappingConfig
from server.mapping.tsdf import TSDFMap
from server.pipeline import ground_truth_pose_at
from server.sessions.processes import mapper as mapper_module
from server.sessions.processes.mapper import Mapper
from tests.conftest import missing
from tests.support.paths import SHARED_DATA

DATA = SHARED_DATA / "synthetic_room0"


def _method(path) -> set[int]:
    with zipfile.ZipFile(path) as z:
        return {i.compress_type for i in z.infolist()}


@pytest.fixture
def mapper() -> Mapper:
    if not DATA.is_dir():
        missing(f"shared data folder {DATA} is absent")
    ds = open_dataset(DATA)
    m = Mapper(MappingConfig())
    for i in range(0, 15, 3):
        T = ground_truth_pose_at(ds, ds.timestamps[i])
        m.fuse(ds[i].colour, ds[i].depth, ds.intrinsics, T)
    return m


def test_periodic_snapshots_store_the_map_and_write_its_points_now_and_then(
    mapper, tmp_path, monkeypatch
):
    clock = [1000.0]
    monkeypatch.setattr(mapper_module.time, "monotonic", lambda: clock[0])
    first, second, later, last = (tmp_path / n for n in ("first", "second", "later", "last"))
    for folder in (first, second, later, last):
        folder.mkdir()

    # The first periodic snapshot has both files: a crash leaves a map.ply to download.
    assert mapper.save(first, periodic=True) == ["map.npz", "map.ply"]
    assert _method(first / "map.npz") == {zipfile.ZIP_STORED}
    # Within PERIODIC_PLY_EVERY_S of it, the map's observations only.
    clock[0] += mapper_module.PERIODIC_PLY_EVERY_S - 1
    assert mapper.save(second, periodic=True) == ["map.npz"]
    assert not (second / "map.ply").exists()
    clock[0] += 1
    assert mapper.save(later, periodic=True) == ["map.npz", "map.ply"]
    # A snapshot asked for, or the session's last: both files, the npz deflated.
    assert mapper.save(last) == ["map.npz", "map.ply"]
    assert _method(last / "map.npz") == {zipfile.ZIP_DEFLATED}
    assert (last / "map.npz").stat().st_size < (first / "map.npz").stat().st_size / 2

    # The stored file holds the very map the deflated one does.
    stored, deflated = TSDFMap.load(second / "map.npz"), TSDFMap.load(last / "map.npz")
    for a, b in zip(stored.occupancy(0.05), deflated.occupancy(0.05), strict=True):
        np.testing.assert_array_equal(a, b)
    # And map.ply, when written, is the map's surface as the last snapshot's is.
    points = [np.asarray(o3d.io.read_point_cloud(str(f / "map.ply")).points) for f in (later, last)]
    assert len(points[0]) == len(points[1]) > 1000
    assert np.abs(np.sort(points[0], axis=0) - np.sort(points[1], axis=0)).max() < 1e-4
