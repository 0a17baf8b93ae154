"""The TSDF map on real frames of the synthetic room with its exact ground-truth poses."""

from __future__ import annotations

import zipfile

import numpy as np
import open3d as o3d
import pytest
from scipy.spatial import cKDTree

from server.datasets import open_dataset
from server.geometry import backproject
from server.mapping.frame_input import at_depth_size
from server.mapping.preview import MapPreview
from server.mapping.tsdf import TSDFConfig, TSDFMap
from server.pipeline import ground_truth_pose_at
from server.registration.preprocess import resample_depth
from server.simulation.flight_map import FlightMap
from tests.conftest import missing
from tests.support.paths import SHARED_DATA

DATA = SHARED_DATA / "synthetic_room0"
VOXEL_M = 0.02
FUSED = range(0, 30, 3)  # ten frames: every third of the first thirty


def small_config(**overrides) -> TSDFConfig:
    return TSDFConfig(**{"voxel_m": VOXEL_M, "block_count": 1000, **overrides})


@pytest.fixture(scope="module")
def room():
    if not DATA.is_dir():
        missing(f"shared data folder {DATA} is absent")
    return open_dataset(DATA)


def pose(ds, i: int) -> np.ndarray:
    T = ground_truth_pose_at(ds, ds.timestamps[i])
    assert T is not None, f"no ground truth for frame {i}"
    return T


def fuse(ds, tsdf: TSDFMap, indices) -> None:
    for i in indices:
        frame = ds[i]
        tsdf.integrate(frame.colour, frame.depth, ds.intrinsics, pose(ds, i))


def measured_surface(ds, indices, stride: int = 2, max_depth_m: float = 4.0) -> np.ndarray:
    """The frames' depth up to the map's range, back-projected to the world frame with the true
    poses, (N, 3) metres."""
    clouds = []
    for i in indices:
        depth = ds[i].depth
        points, _ = backproject(np.where(depth <= max_depth_m, depth, 0), ds.intrinsics, stride)
        T = pose(ds, i)
        clouds.append(points @ T[:3, :3].T + T[:3, 3])
    return np.concatenate(clouds)


@pytest.fixture(scope="module")
def fused(room) -> TSDFMap:
    """A map of the ten fused frames; tests must not change it."""
    tsdf = TSDFMap(small_config())
    fuse(room, tsdf, FUSED)
    return tsdf


def test_extracted_points_lie_on_the_measured_surface(room, fused):
    points, colours = fused.point_cloud()
    assert len(points) > 10_000
    assert points.dtype == np.float64 and colours.shape == points.shape
    assert colours.min() >= 0 and colours.max() <= 1 and colours.std() > 0.02
    distances, _ = cKDTree(measured_surface(room, FUSED)).query(points)
    assert np.median(distances) < 1.5 * VOXEL_M, f"median {np.median(distances) * 1000:.1f} mm"
    assert fused.stats()["frames_integrated"] == len(FUSED)


def test_a_map_has_a_surface_exactly_when_its_mesh_has_triangles(room):
    """has_surface tells the page when mesh.ply stops answering 409: a voxel needs more than
    min_weight observations (four frames here) before marching cubes shows it."""
    tsdf = TSDFMap(small_config())
    answers = []
    for i in FUSED[:5]:
        fuse(room, tsdf, [i])
        answers.append((tsdf.has_surface(), tsdf.mesh().has_triangles()))
        assert answers[-1][0] == answers[-1][1], answers
    assert [has for has, _ in answers] == [False, False, False, True, True]
    assert not TSDFMap(small_config()).has_surface()


def test_point_cloud_and_mesh_ply_round_trip(fused, tmp_path):
    fused.write_point_cloud_ply(tmp_path / "map.ply")
    cloud = o3d.io.read_point_cloud(str(tmp_path / "map.ply"))
    assert len(cloud.points) > 1000 and cloud.has_colors()
    assert len(cloud.points) == len(fused.point_cloud()[0])

    fused.write_mesh_ply(tmp_path / "mesh.ply")
    mesh = o3d.io.read_triangle_mesh(str(tmp_path / "mesh.ply"))
    assert len(mesh.triangles) > 1000 and mesh.has_vertex_colors()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["map.ply", "mesh.ply"]  # no temp files


def test_save_and_load_restore_the_same_surface(fused, tmp_path):
    fused.save(tmp_path / "map.npz")
    restored = TSDFMap.load(tmp_path / "map.npz", small_config())
    before, after = fused.point_cloud()[0], restored.point_cloud()[0]
    assert abs(len(after) - len(before)) <= 0.01 * len(before)
    assert np.median(cKDTree(before).query(after)[0]) < 1e-4
    stats = restored.stats()
    assert stats["frames_integrated"] == len(FUSED)
    assert stats["active_blocks"] == fused.stats()["active_blocks"]
    # Colours and the drone's occupancy come back too.
    colours_before, colours_after = fused.point_cloud()[1], restored.point_cloud()[1]
    assert abs(colours_after.mean() - colours_before.mean()) < 2 / 255
    for a, b in zip(fused.occupancy(0.05), restored.occupancy(0.05), strict=True):
        np.testing.assert_array_equal(a, b)
    # Compact: TSDF as float16 and colour as uint8, deflated - well under a third of the
    # float32 grid's 20 bytes per voxel.
    grid_bytes = stats["active_blocks"] * small_config().block_resolution ** 3 * 20
    assert (tmp_path / "map.npz").stat().st_size < grid_bytes / 3


def test_an_uncompressed_save_loads_back_the_same_map(fused, tmp_path):
    """A periodic snapshot stores its arrays as they are (no deflate, less CPU): the map read
    back is the compressed file's, array for array."""
    fused.save(tmp_path / "deflated.npz")
    fused.save(tmp_path / "stored.npz", compress=False)
    with zipfile.ZipFile(tmp_path / "stored.npz") as z:
        assert {i.compress_type for i in z.infolist()} == {zipfile.ZIP_STORED}
    with zipfile.ZipFile(tmp_path / "deflated.npz") as z:
        assert {i.compress_type for i in z.infolist()} == {zipfile.ZIP_DEFLATED}
    assert (tmp_path / "stored.npz").stat().st_size > 2 * (tmp_path / "deflated.npz").stat().st_size
    with np.load(tmp_path / "stored.npz") as a, np.load(tmp_path / "deflated.npz") as b:
        assert sorted(a.files) == sorted(b.files)
        for name in a.files:
            np.testing.assert_array_equal(a[name], b[name])
    restored = TSDFMap.load(tmp_path / "stored.npz", small_config())
    for x, y in zip(fused.occupancy(0.05), restored.occupancy(0.05), strict=True):
        np.testing.assert_array_equal(x, y)


def test_a_map_saved_in_open3ds_own_layout_still_loads(fused, tmp_path):
    """Rooms saved before the compact format (Open3D's VoxelBlockGrid layout) keep opening."""
    fused._grid.save(str(tmp_path / "old.npz"))
    restored = TSDFMap.load(tmp_path / "old.npz")
    before, after = fused.point_cloud()[0], restored.point_cloud()[0]
    assert abs(len(after) - len(before)) <= 0.01 * len(before)
    assert np.median(cKDTree(before).query(after)[0]) < 1e-4


def test_a_damaged_or_foreign_map_file_is_refused_clearly(fused, tmp_path):
    from server.mapping.tsdf import MapError

    fused.save(tmp_path / "map.npz")
    with np.load(tmp_path / "map.npz") as stored:
        arrays = dict(stored)
    np.savez(tmp_path / "future.npz", **{**arrays, "format": np.array("dronesim-tsdf-9")})
    with pytest.raises(MapError, match="unknown map format"):
        TSDFMap.load(tmp_path / "future.npz")
    np.savez(tmp_path / "cut.npz", **{**arrays, "tsdf": arrays["tsdf"][:-1]})
    with pytest.raises(MapError, match="shape"):
        TSDFMap.load(tmp_path / "cut.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip file")
    with pytest.raises(MapError, match="cannot load"):
        TSDFMap.load(tmp_path / "junk.npz")


def test_invalid_depth_is_ignored(room):
    tsdf = TSDFMap(small_config())
    fuse(room, tsdf, range(0, 9, 3))
    count = len(tsdf.point_cloud()[0])
    frame = room[9]
    blank = np.full_like(frame.depth, np.nan)
    assert tsdf.integrate(frame.colour, blank, room.intrinsics, pose(room, 9)) == 0
    assert len(tsdf.point_cloud()[0]) == count

    # Half the image NaN, a stripe of inf and one of negative depth: the rest is still fused.
    depth = frame.depth.copy()
    depth[:, : depth.shape[1] // 2] = np.nan
    depth[:20] = np.inf
    depth[-20:] = -1.0
    tsdf.integrate(frame.colour, depth, room.intrinsics, pose(room, 9))
    points, colours = tsdf.point_cloud()
    assert np.all(np.isfinite(points)) and np.all(np.isfinite(colours))
    distances, _ = cKDTree(measured_surface(room, [0, 3, 6, 9])).query(points)
    assert np.percentile(distances, 99) < 5 * VOXEL_M


def test_occupancy_marks_camera_path_free_and_surfaces_occupied(room, fused):
    cell = 0.05
    origin, occupied, observed = fused.occupancy(cell)
    assert occupied.shape == observed.shape and occupied.ndim == 3
    assert not np.any(occupied & ~observed)

    def cells(points):
        ijk = np.floor((points - origin) / cell).astype(int)
        inside = np.all((ijk >= 0) & (ijk < occupied.shape), axis=1)
        return ijk, inside

    cameras = np.array([pose(room, i)[:3, 3] for i in FUSED])
    ijk, inside = cells(cameras)
    assert inside.all()
    i, j, k = ijk.T
    assert observed[i, j, k].all() and not occupied[i, j, k].any()

    surface = measured_surface(room, FUSED, stride=8)
    ijk, inside = cells(surface)
    i, j, k = ijk[inside].T
    assert inside.mean() > 0.98
    assert occupied[i, j, k].mean() > 0.9, f"only {occupied[i, j, k].mean():.1%} occupied"
    # Free space was carved: most observed cells are free.
    assert (observed & ~occupied).sum() > occupied.sum()


def test_take_preview_is_bounded_and_returns_only_new_content(room):
    tsdf = TSDFMap(small_config())
    fuse(room, tsdf, FUSED)
    points, colours = tsdf.take_preview(max_points=500)
    assert len(points) == 500 and colours.shape == (500, 3)
    seen = [points]
    while len(batch := tsdf.take_preview(max_points=5000)[0]):
        seen.append(batch)
    seen = np.concatenate(seen)
    assert len(np.unique(np.floor(seen / VOXEL_M), axis=0)) == len(seen)  # one per voxel
    assert len(seen) > 0.5 * len(tsdf.point_cloud()[0])

    assert tsdf.integrate(room[120].colour, room[120].depth, room.intrinsics, pose(room, 120)) > 0
    fuse(room, tsdf, [121, 122, 123])  # new surface shows once seen min_weight times
    fresh, _ = tsdf.take_preview(max_points=10**6)
    assert len(fresh) > 0
    assert np.median(cKDTree(seen).query(fresh)[0]) > VOXEL_M  # mostly new surface
    assert len(tsdf.take_preview(max_points=10**6)[0]) == 0


def test_occupancy_in_a_rotated_grid_frame(room, fused):
    """A gravity-aligned grid: the same cameras and surfaces land in the rotated cells."""
    cell = 0.05
    angle = np.deg2rad(30.0)
    R = np.array([[1, 0, 0], [0, np.cos(angle), -np.sin(angle)], [0, np.sin(angle), np.cos(angle)]])
    origin, occupied, observed = fused.occupancy(cell, R_grid_world=R)

    def cells(points_world):
        return np.floor((points_world @ R.T - origin) / cell).astype(int)

    i, j, k = cells(np.array([pose(room, i)[:3, 3] for i in FUSED])).T
    assert observed[i, j, k].all() and not occupied[i, j, k].any()
    ijk = cells(measured_surface(room, FUSED, stride=8))
    inside = np.all((ijk >= 0) & (ijk < occupied.shape), axis=1)
    assert inside.mean() > 0.98
    assert occupied[tuple(ijk[inside].T)].mean() > 0.9


def test_occupancy_updates_merge_into_exactly_the_full_grid_and_flight_map(room):
    """Sub-boxes from occupancy_update, merged frame by frame, are the full occupancy grid; fed
    into a flight map with update_region, its distance field is the full rebuild's."""
    cell = 0.05
    angle = np.deg2rad(20.0)
    R = np.array([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
    tsdf = TSDFMap(small_config())
    fuse(room, tsdf, [0, 3])
    origin, occupied, observed = tsdf.occupancy_update(cell, R)  # the first: everything so far
    full = tsdf.occupancy(cell, R)
    np.testing.assert_allclose(origin, full[0])
    np.testing.assert_array_equal(occupied, full[1])
    np.testing.assert_array_equal(observed, full[2])
    flight_map = FlightMap(cell, max_distance_m=0.5)
    flight_map.update(origin, occupied, observed)
    assert tsdf.occupancy_update(cell, R) is None  # nothing fused since
    for i in [6, 40, 9, 80]:  # new views grow the grid, revisits change what is inside it
        fuse(room, tsdf, [i])
        box_origin, box_occupied, box_observed = tsdf.occupancy_update(cell, R)
        # The box agrees with the full grid where they overlap and is unobserved elsewhere.
        full = tsdf.occupancy(cell, R)
        at = np.round((box_origin - full[0]) / cell).astype(int)
        assert np.all(at >= 0) and np.all(at + box_occupied.shape <= full[1].shape)
        box = tuple(slice(a, a + n) for a, n in zip(at, box_occupied.shape, strict=True))
        np.testing.assert_array_equal(box_occupied, full[1][box])
        np.testing.assert_array_equal(box_observed, full[2][box])
        flight_map.update_region(box_origin, box_occupied, box_observed)
        rebuilt = FlightMap(cell, max_distance_m=0.5)
        rebuilt.update(*full)
        # The same drone's world: blocked cells and field on the lattice, outside each grid
        # unobserved (blocked). The merged map may reach a plane further: a cell seen only
        # through a surface voxel that has since left the surface band (the TSDF's voxels are
        # sampled for what was seen, occupancy_update's docstring) is unobserved in the full
        # grid now, and blocked in either.
        np.testing.assert_array_equal(
            on_lattice(flight_map, rebuilt), on_lattice(rebuilt, flight_map)
        )
        # The field of either is the infinite lattice's (flight_map.py): equal where both hold it.
        inside = shared(flight_map, rebuilt)
        np.testing.assert_array_equal(flight_map.esdf[inside[0]], rebuilt.esdf[inside[1]])


def on_lattice(flight_map: FlightMap, other: FlightMap) -> np.ndarray:
    """``flight_map``'s blocked cells over the box both maps span (on one lattice), its
    outside as FlightMap counts it: unobserved, so blocked."""
    cell = flight_map.voxel_m
    lo = np.minimum(flight_map.origin, other.origin)
    hi = np.maximum(
        flight_map.origin + np.array(flight_map.shape) * cell,
        other.origin + np.array(other.shape) * cell,
    )
    blocked = np.ones(tuple(np.round((hi - lo) / cell).astype(int)), bool)
    at = np.round((flight_map.origin - lo) / cell).astype(int)
    blocked[tuple(slice(a, a + n) for a, n in zip(at, flight_map.shape, strict=True))] = (
        flight_map.blocked
    )
    return blocked


def shared(a: FlightMap, b: FlightMap) -> tuple[tuple[slice, ...], tuple[slice, ...]]:
    """Index boxes of the cells both grids hold, into a's and into b's."""
    lo = np.maximum(a.origin, b.origin)
    hi = np.minimum(
        a.origin + np.array(a.shape) * a.voxel_m, b.origin + np.array(b.shape) * b.voxel_m
    )
    n = np.round((hi - lo) / a.voxel_m).astype(int)
    at_a = np.round((lo - a.origin) / a.voxel_m).astype(int)
    at_b = np.round((lo - b.origin) / b.voxel_m).astype(int)
    return (
        tuple(slice(i, i + k) for i, k in zip(at_a, n, strict=True)),
        tuple(slice(i, i + k) for i, k in zip(at_b, n, strict=True)),
    )


def _merged(grid, box) -> None:
    """Write the update ``box`` (origin, occupied, observed) into ``grid`` (same lattice)."""
    at = np.round((box[0] - grid[0]) / 0.05).astype(int)
    assert np.all(at >= 0) and np.all(at + box[1].shape <= grid[1].shape)
    region = tuple(slice(a, a + n) for a, n in zip(at, box[1].shape, strict=True))
    grid[1][region], grid[2][region] = box[1], box[2]


def test_two_drones_reading_one_map_each_get_every_change(room):
    """Two readers of one map (two phones' drones in a shared room): one reading does not
    take the changes from the other. A reader's first update is the whole grid, whenever it
    comes; each then gets the boxes of what was fused since its own last update, which merge
    into the full grid; nothing fused since its own last update gives None."""
    cell, R = 0.05, np.eye(3)
    tsdf = TSDFMap(small_config())
    fuse(room, tsdf, [0, 3])
    first = tsdf.occupancy_update(cell, R, reader="owner")
    fuse(room, tsdf, [40])
    later = tsdf.occupancy_update(cell, R, reader="joined")  # its first: the whole map now
    full = tsdf.occupancy(cell, R)
    np.testing.assert_array_equal(later[1], full[1])
    np.testing.assert_array_equal(later[2], full[2])
    assert tsdf.occupancy_update(cell, R, reader="joined") is None
    box = tsdf.occupancy_update(cell, R, reader="owner")  # frame 40's changes, still unread
    assert box is not None
    # The owner's grid, grown to the full grid's extent, then updated with its box.
    grid = (full[0], np.zeros_like(full[1]), np.zeros_like(full[2]))
    _merged(grid, first)
    _merged(grid, box)
    np.testing.assert_array_equal(grid[1], full[1])
    np.testing.assert_array_equal(grid[2], full[2])
    fuse(room, tsdf, [80])
    assert tsdf.occupancy_update(cell, R, reader="owner") is not None
    assert tsdf.occupancy_update(cell, R, reader="joined") is not None  # not taken by owner's


def test_a_phones_small_depth_fused_at_its_own_size_gives_the_map_of_it_upsampled(room):
    """A phone's depth is 1/4 of its colour each way (ARCore). The tracker works on it resampled
    to the colour's size (nearest neighbour); a plain frame is fused at the depth's own size
    with the colour averaged to it (server/sessions/runtime/tracking.py), 1/16 of the pixels to
    send to the mapper. The surface, its colours and the preview are those of the resampled
    frame."""
    K = room.intrinsics
    small_map, resampled_map = TSDFMap(small_config()), TSDFMap(small_config())
    small_preview, resampled_preview = MapPreview(), MapPreview()
    small_points, resampled_points = [], []
    for i in FUSED:
        frame, T = room[i], pose(room, i)
        depth = np.ascontiguousarray(frame.depth[1::4, 1::4])  # 160 x 120
        resampled = resample_depth(depth, K.width, K.height)
        small_map.integrate(at_depth_size(frame.colour, depth), depth, K, T)
        resampled_map.integrate(frame.colour, resampled, K, T)
        small_points.append(small_preview.new_points(frame.colour, depth, K, T, 4000)[0])
        resampled_points.append(
            resampled_preview.new_points(frame.colour, resampled, K, T, 4000)[0]
        )
    (small, small_rgb), (full, full_rgb) = small_map.point_cloud(), resampled_map.point_cloud()
    assert 0.8 < len(small) / len(full) < 1.25, (len(small), len(full))
    # As close to the measured surface (every pixel's depth): 4.9 against 4.9 mm (median).
    truth = cKDTree(measured_surface(room, FUSED))
    off_small, off_full = truth.query(small)[0], truth.query(full)[0]
    assert np.median(off_small) < np.median(off_full) + 0.0005, (off_small, off_full)
    assert np.percentile(off_small, 95) < np.percentile(off_full, 95) + 0.001
    distance, nearest = cKDTree(full).query(small)
    close = distance < 0.005
    # The colours averaged: 6 of 255 apart on average where the surfaces meet.
    assert np.abs(small_rgb[close] - full_rgb[nearest[close]]).mean() < 0.04
    small_cloud, full_cloud = np.concatenate(small_points), np.concatenate(resampled_points)
    assert 0.8 < len(small_cloud) / len(full_cloud) < 1.25, (len(small_cloud), len(full_cloud))
    assert np.median(cKDTree(full_cloud).query(small_cloud)[0]) < 0.04
