"""Flight map: the distance field against brute force, incremental updates against a full
rebuild, unknown space, and the queries the planner and the collision checks use."""

from __future__ import annotations

import numpy as np
import pytest

from server.simulation import esdf, scenes
from server.simulation.flight_map import FlightMap, FlightMapError
from server.simulation.map_regions import Region


def brute_force_field(blocked: np.ndarray, voxel_m: float, max_m: float, outside: bool):
    """Cell-centre signed distance by exhaustive search, on the grid ringed by outside cells."""
    ringed = np.pad(blocked, 1, constant_values=outside)
    cells = np.argwhere(np.ones_like(ringed))
    blocked_cells, free_cells = np.argwhere(ringed), np.argwhere(~ringed)
    field = np.empty(ringed.shape)
    for c in cells:
        is_blocked = ringed[tuple(c)]
        other = free_cells if is_blocked else blocked_cells
        d = np.sqrt(((other - c) ** 2).sum(1)).min() if len(other) else np.inf
        field[tuple(c)] = (-(d - 0.5) if is_blocked else d - 0.5) * voxel_m
    return np.clip(field, -max_m, max_m)[1:-1, 1:-1, 1:-1]


def box_distance(points, blocked, origin, voxel_m):
    """Exact distance from points to the union of blocked cells (0 inside)."""
    lo = origin + np.argwhere(blocked) * voxel_m
    p = points[:, None]
    gap = np.maximum(np.maximum(lo[None] - p, p - lo[None] - voxel_m), 0)
    return np.linalg.norm(gap, axis=2).min(axis=1)


@pytest.mark.parametrize("unknown_is_free", [False, True])
def test_field_at_cell_centres_equals_brute_force(unknown_is_free):
    rng = np.random.default_rng(3)
    for _ in range(3):
        occupied = rng.random((9, 8, 7)) < 0.1
        observed = rng.random((9, 8, 7)) < 0.9
        flight_map = FlightMap(0.1, unknown_is_free, max_distance_m=0.35)
        flight_map.update(np.array([0.3, -0.2, 0.1]), occupied, observed)
        blocked = occupied if unknown_is_free else occupied | ~observed
        expected = brute_force_field(blocked, 0.1, 0.35, outside=not unknown_is_free)
        np.testing.assert_allclose(flight_map.esdf, expected, atol=1e-6)
        centres = flight_map.cell_centres(np.argwhere(np.ones(blocked.shape)))
        np.testing.assert_allclose(flight_map.distance(centres), expected.ravel(), atol=1e-6)


def test_distance_between_centres_is_close_to_the_exact_distance_to_blocked_cells():
    rng = np.random.default_rng(4)
    v = 0.1
    occupied = rng.random((10, 9, 8)) < 0.08
    flight_map = FlightMap(v, unknown_is_free=True, max_distance_m=5.0)
    flight_map.update(np.zeros(3), occupied, np.ones_like(occupied))
    points = rng.uniform(0, 1, (3000, 3)) * np.array(occupied.shape) * v
    exact = box_distance(points, occupied, np.zeros(3), v)
    d = flight_map.distance(points)
    outside = exact > 0
    # Stated in the module doc: at most ~0.6 voxel too high (isolated cells), never far too low.
    assert np.all(d[outside] - exact[outside] <= 0.65 * v)
    assert np.all(d[outside] - exact[outside] >= -0.5 * v)
    assert np.all(d[~outside] <= 0.65 * v)


def test_distance_to_scene_boxes_is_within_half_a_voxel():
    rng = np.random.default_rng(5)
    for make in (scenes.room_with_door, scenes.box_in_the_way):
        scene = make()
        bounds = scene.flight_map.bounds
        points = rng.uniform(bounds.lo, bounds.hi, (5000, 3))
        exact = scene.true_distance(points)
        near = (exact > 0) & (exact < 0.9)  # below the 1 m clip
        err = scene.flight_map.distance(points)[near] - exact[near]
        assert np.abs(err).max() <= 0.5 * scene.flight_map.voxel_m


def test_incremental_updates_equal_a_full_rebuild():
    rng = np.random.default_rng(6)
    v = 0.05
    incremental = FlightMap(v, max_distance_m=0.4)
    shape, origin = np.array([40, 36, 24]), np.array([0.3, -0.1, 0.0])
    occupied = rng.random(shape) < 0.02
    observed = np.ones(shape, bool)
    observed[30:] = False
    incremental.update(origin, occupied, observed)
    for step in range(8):
        # Grow on random sides (sometimes none), then change a small block somewhere.
        grow_lo = rng.integers(0, 3, 3) * (step % 2)
        grow_hi = rng.integers(0, 3, 3) * (step % 3 == 0)
        new_shape = shape + grow_lo + grow_hi
        new_occ, new_obs = np.zeros(new_shape, bool), np.zeros(new_shape, bool)
        inner = tuple(slice(a, a + n) for a, n in zip(grow_lo, shape, strict=True))
        new_occ[inner], new_obs[inner] = occupied, observed
        corner = rng.integers(0, new_shape - 5)
        block = tuple(slice(a, a + 4) for a in corner)
        new_occ[block], new_obs[block] = rng.random((4, 4, 4)) < 0.4, True
        origin = origin - grow_lo * v
        before = incremental.version
        changed = incremental.update(origin, new_occ, new_obs)
        full = FlightMap(v, max_distance_m=0.4)
        full.update(origin, new_occ, new_obs)
        np.testing.assert_array_equal(incremental.esdf, full.esdf)
        np.testing.assert_array_equal(incremental.origin, full.origin)
        assert incremental.version == before + 1
        assert changed is not None
        assert changed.contains(incremental.cell_centres(corner[None] + 1))[0]
        shape, occupied, observed = new_shape, new_occ, new_obs
    # Shrinking and shifting the grid is exact too; an identical grid changes nothing.
    small_origin = origin + np.array([2, 1, 0]) * v
    small = (occupied[2:-3, 1:, :-2], observed[2:-3, 1:, :-2])
    incremental.update(small_origin, *small)
    full = FlightMap(v, max_distance_m=0.4)
    full.update(small_origin, *small)
    np.testing.assert_array_equal(incremental.esdf, full.esdf)
    version = incremental.version
    assert incremental.update(small_origin, *small) is None
    assert incremental.version == version


def test_unknown_space_is_blocked_by_default_and_free_when_configured():
    occupied = np.zeros((20, 20, 10), bool)
    observed = np.zeros_like(occupied)
    observed[:10] = True  # the half x < 0.5 m was seen (empty), the rest never
    seen, unseen, beyond = [0.25, 0.5, 0.25], [0.75, 0.5, 0.25], [1.5, 0.5, 0.25]
    cautious = FlightMap(0.05)
    cautious.update(np.zeros(3), occupied, observed)
    assert cautious.distance(np.array([unseen, beyond])).max() < 0
    assert cautious.distance(np.array(seen)) > 0
    daring = FlightMap(0.05, unknown_is_free=True)
    daring.update(np.zeros(3), occupied, observed)
    assert daring.distance(np.array([seen, unseen, beyond])).min() > 0.2


def test_gradient_points_away_from_the_wall_and_matches_finite_differences():
    scene = scenes.box_in_the_way()
    m = scene.flight_map
    points = np.array([[1.7, 1.5, 1.0], [2.5, 0.4, 0.9], [3.4, 2.6, 1.2]])
    g = m.gradient(points)
    np.testing.assert_allclose(g[0], [-1, 0, 0], atol=0.05)  # 0.3 m before the box's x face
    np.testing.assert_allclose(g[1], [0, -1, 0], atol=0.05)  # between box and the y = 0 wall
    h = 1e-5
    for axis in range(3):
        e = np.zeros(3)
        e[axis] = h
        fd = (m.distance(points + e) - m.distance(points - e)) / (2 * h)
        np.testing.assert_allclose(g[:, axis], fd, atol=1e-4)


def test_segment_checks_see_a_wall_between_samples():
    m = scenes.room_with_door().flight_map
    a = np.array([[1.0, 0.6, 1.2], [1.0, 1.65, 1.2], [1.0, 0.6, 1.2]])
    b = np.array([[3.0, 0.6, 1.2], [3.0, 1.65, 1.2], [1.5, 0.6, 1.2]])
    np.testing.assert_array_equal(m.segments_free(a, b, 0.15), [False, True, True])
    assert m.segment_is_free(a[1], b[1], 0.15) is True
    assert m.segment_clearance(a[0], b[0]) < 0  # through the wall
    assert m.segment_clearance(a[1], b[1]) == pytest.approx(0.45, abs=0.03)  # door half-width
    # The batch form is the single one, segment by segment.
    many = m.segment_clearances(a, b)
    assert many.shape == (3,)
    assert many.tolist() == [m.segment_clearance(p, q) for p, q in zip(a, b, strict=True)]
    assert type(m.segment_clearance(a[0], b[0])) is float
    assert m.segment_clearances(np.empty((0, 3)), np.empty((0, 3))).shape == (0,)


def test_nearest_free_and_random_free_points_have_the_clearance():
    scene = scenes.box_in_the_way()
    m = scene.flight_map
    inside_box = np.array([2.1, 1.5, 1.0])  # 0.1 m inside the box's x = 2 face
    p = m.nearest_free(inside_box, 0.2)
    assert m.distance(p) >= 0.2
    assert np.linalg.norm(p - inside_box) < 0.4  # just outside the face
    assert m.nearest_free(inside_box, 5.0) is None
    points = m.random_free_points(200, 0.3, np.random.default_rng(0))
    assert points.shape == (200, 3)
    assert np.all(m.distance(points) >= 0.3)
    assert np.all(scene.true_distance(points) >= 0.3 - 0.5 * m.voxel_m)


def test_from_boxes_occupies_every_cell_a_box_overlaps():
    m = FlightMap.from_boxes([0, 0, 0], [1, 1, 1], [([0.12, 0.12, 0.12], [0.18, 0.31, 0.2])], 0.1)
    assert m.shape == (10, 10, 10)
    assert np.argwhere(m.blocked).tolist() == [[1, 1, 1], [1, 2, 1], [1, 3, 1]]


def test_malformed_grids_are_rejected():
    m = FlightMap(0.05)
    with pytest.raises(FlightMapError, match="one shape"):
        m.update(np.zeros(3), np.zeros((4, 4, 4), bool), np.zeros((4, 4, 3), bool))
    with pytest.raises(FlightMapError, match="origin"):
        m.update(np.array([0, np.nan, 0]), np.zeros((4, 4, 4), bool), np.zeros((4, 4, 4), bool))


def _merge(grid, origin, box_origin, occupied, observed, written, v):
    """The test's own merge of a sub-box into (occupied, observed) grids: grown to hold it
    (new cells unobserved), the written cells overwritten. Returns (origin, occupied, observed)."""
    occ, obs = grid
    at = np.round((box_origin - origin) / v).astype(int)
    lo = np.minimum(at, 0)
    hi = np.maximum(np.array(occ.shape), at + occupied.shape)
    new_occ, new_obs = np.zeros(hi - lo, bool), np.zeros(hi - lo, bool)
    inner = tuple(slice(a, a + n) for a, n in zip(-lo, occ.shape, strict=True))
    new_occ[inner], new_obs[inner] = occ, obs
    box = tuple(slice(a, a + n) for a, n in zip(at - lo, occupied.shape, strict=True))
    new_occ[box][written], new_obs[box][written] = occupied[written], observed[written]
    return origin + lo * v, (new_occ, new_obs)


@pytest.mark.parametrize("unknown_is_free", [False, True])
def test_sub_box_updates_equal_a_full_rebuild_and_stay_local(unknown_is_free, monkeypatch):
    rng = np.random.default_rng(8)
    v, max_m = 0.05, 0.3
    shape, origin = np.array([50, 44, 30]), np.array([0.3, -0.1, 0.0])
    grid = (rng.random(shape) < 0.02, np.ones(shape, bool))
    grid[1][40:] = False
    incremental = FlightMap(v, unknown_is_free, max_distance_m=max_m)
    incremental.update(origin, *grid)
    windows = []  # the blocks whose field is computed from scratch
    compute = esdf.signed_distance

    def recording(blocked, voxel_m, max_distance_m):
        windows.append(blocked.size)
        return compute(blocked, voxel_m, max_distance_m)

    monkeypatch.setattr(esdf, "signed_distance", recording)
    reach = incremental._reach
    for step in range(10):
        # A small box somewhere in or around the grid (sometimes sticking out, growing it),
        # writing only some of its cells.
        size = rng.integers(2, 7, 3)
        at = rng.integers(-3, np.array(grid[0].shape) - 2)
        box_origin = origin + at * v
        occupied, observed = rng.random(size) < 0.4, rng.random(size) < 0.9
        written = rng.random(size) < 0.8 if step % 2 else np.ones(size, bool)
        windows.clear()
        inside = np.all(at >= 0) and np.all(at + size <= grid[0].shape)
        changed = incremental.update_region(box_origin, occupied, observed, written)
        largest_window = max(windows, default=0)
        origin, grid = _merge(grid, origin, box_origin, occupied, observed, written, v)
        full = FlightMap(v, unknown_is_free, max_distance_m=max_m)
        full.update(origin, *grid)
        np.testing.assert_allclose(incremental.origin, full.origin, atol=1e-12)
        np.testing.assert_array_equal(incremental.blocked, full.blocked)
        np.testing.assert_array_equal(incremental.esdf, full.esdf)
        # Local: a box inside the grid computes no window beyond the box grown by twice the
        # field's reach (one reach for the cells that may change, one for what they see).
        # (A box that grows the grid also recomputes the new faces near the old grid.)
        if inside:
            assert largest_window <= np.prod(size + 4 * reach + 2)
        if changed is not None:
            assert changed.contains(box_origin + (np.array(size) / 2) * v, margin_m=v)[0]
    # Writing what is already there changes nothing.
    version = incremental.version
    assert incremental.update_region(origin, *grid) is None
    assert incremental.version == version


def test_merged_regions_equal_the_regions_applied_one_after_the_other():
    rng = np.random.default_rng(9)
    v = 0.05
    base = FlightMap.from_boxes(
        (0, 0, 0), (2.0, 1.5, 1.0), [((0.5, 0.5, 0.0), (0.7, 0.7, 1.0))], v, max_distance_m=0.4
    )
    one_by_one = FlightMap.from_boxes(
        (0, 0, 0), (2.0, 1.5, 1.0), [((0.5, 0.5, 0.0), (0.7, 0.7, 1.0))], v, max_distance_m=0.4
    )
    regions = []
    for at in ([3, 4, 2], [6, 5, 3], [38, 28, 18]):  # two overlapping, one sticking out
        size = (6, 5, 4)
        regions.append(
            Region.whole(np.array(at) * v, rng.random(size) < 0.5, rng.random(size) < 0.9)
        )
        one_by_one.update_region(regions[-1].origin, regions[-1].occupied, regions[-1].observed)
    merged = regions[0].merged(regions[1], v).merged(regions[2], v)
    assert merged.occupied.shape == (41, 29, 20) and not merged.written.all()
    base.update_region(merged.origin, merged.occupied, merged.observed, merged.written)
    np.testing.assert_array_equal(base.blocked, one_by_one.blocked)
    np.testing.assert_array_equal(base.esdf, one_by_one.esdf)


def test_sub_boxes_must_sit_on_the_lattice():
    flight_map = FlightMap.from_boxes((0, 0, 0), (1, 1, 1), [], 0.1)
    with pytest.raises(FlightMapError, match="lattice"):
        flight_map.update_region(
            np.array([0.05, 0.0, 0.0]), np.zeros((2, 2, 2), bool), np.ones((2, 2, 2), bool)
        )
