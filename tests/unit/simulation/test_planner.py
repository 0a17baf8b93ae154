"""Route planner: routes through a door, along a corridor and around a box keep the radius from
the true geometry, respect the speed and acceleration limits, and every failure says why."""

from __future__ import annotations

import numpy as np
import pytest

from server.simulation import scenes
from server.simulation.flight_map import FlightMap
from server.simulation.planner import plan_path, route_is_clear
from server.simulation.route import PlanningError, Reason

RADIUS = 0.15


@pytest.fixture(scope="module")
def scene_maps():
    return {name: make() for name, make in scenes.SCENES.items()}


def dense(points: np.ndarray, step: float = 0.005) -> np.ndarray:
    """The polyline through points, resampled every ``step`` metres."""
    out = [points[:1]]
    for a, b in zip(points[:-1], points[1:], strict=True):
        n = max(1, int(np.ceil(np.linalg.norm(b - a) / step)))
        out.append(a + (b - a) * np.linspace(0, 1, n + 1)[1:, None])
    return np.concatenate(out)


def check_route_keeps_radius(scene, route):
    """The route, its smoothed path and where sample(t) puts the drone all keep RADIUS from the
    scene's true boxes (not just from the grid)."""
    times = np.linspace(0.0, route.duration_s, 2000)
    positions = route.sample(times)[0]
    for samples in (dense(route.points), dense(route.path), positions):
        assert scene.true_distance(samples).min() >= RADIUS
        assert scene.flight_map.distance(samples).min() >= RADIUS
    np.testing.assert_allclose(route.path[0], scene.start)
    np.testing.assert_allclose(route.path[-1], scene.goal)
    np.testing.assert_allclose(positions[-1], scene.goal)


@pytest.mark.parametrize(
    "name, max_ratio", [("room_with_door", 1.6), ("corridor", 1.45), ("box_in_the_way", 1.45)]
)
def test_route_goes_around_obstacles_and_keeps_the_radius(scene_maps, name, max_ratio):
    scene = scene_maps[name]
    assert not scene.flight_map.segment_is_free(scene.start, scene.goal, RADIUS)  # no shortcut
    route = plan_path(scene.flight_map, scene.start, scene.goal, RADIUS)
    check_route_keeps_radius(scene, route)
    straight = np.linalg.norm(scene.goal - scene.start)
    assert straight < route.length_m <= max_ratio * straight


def test_route_through_the_door_passes_the_door(scene_maps):
    scene = scene_maps["room_with_door"]
    route = plan_path(scene.flight_map, scene.start, scene.goal, RADIUS)
    crossing = route.path[np.argmin(np.abs(route.path[:, 0] - 2.0))]
    assert 1.2 + RADIUS <= crossing[1] <= 2.1 - RADIUS and crossing[2] <= 2.0 - RADIUS


def test_route_keeps_to_the_middle_of_the_corridor(scene_maps):
    scene = scene_maps["corridor"]
    route = plan_path(scene.flight_map, scene.start, scene.goal, RADIUS)
    leg = route.path[(route.path[:, 0] > 1.0) & (route.path[:, 0] < 2.0)]
    assert len(leg) and np.all(np.abs(leg[:, 1] - 0.5) < 0.15)  # corridor is y in [0, 1]
    assert np.all(np.abs(leg[:, 2] - 1.0) < 0.15)  # and z in [0, 2]


def test_open_space_gives_a_straight_route(scene_maps):
    scene = scene_maps["box_in_the_way"]
    start, goal = np.array([1.0, 1.5, 1.0]), np.array([1.5, 1.2, 1.3])
    route = plan_path(scene.flight_map, start, goal, RADIUS)
    assert len(route.points) == 2
    assert route.length_m == pytest.approx(np.linalg.norm(goal - start), rel=1e-6)


def test_speed_and_acceleration_limits_hold_along_the_route(scene_maps):
    scene = scene_maps["box_in_the_way"]
    v_max, a_max, climb = 1.2, 1.5, 0.5
    route = plan_path(
        scene.flight_map,
        scene.start,
        scene.goal,
        RADIUS,
        max_speed_m_s=v_max,
        max_accel_m_s2=a_max,
        max_climb_rate_m_s=climb,
    )
    dt = 0.002
    t = np.arange(0.0, route.duration_s + dt, dt)
    position, velocity, acceleration = route.sample(t)
    speed = np.linalg.norm(velocity, axis=1)
    assert speed.max() <= v_max + 1e-6
    assert np.abs(velocity[:, 2]).max() <= climb + 1e-6
    assert np.linalg.norm(acceleration, axis=1).max() <= a_max * 1.02
    assert speed[0] < 1e-9 and speed[-1] < 1e-9
    assert speed.max() > 0.5 * v_max  # it does get going
    # The velocity is the derivative of the position, and the acceleration of the velocity.
    fd_velocity = np.diff(position, axis=0) / dt
    assert np.abs(fd_velocity - 0.5 * (velocity[1:] + velocity[:-1])).max() < 0.05
    fd_acceleration = np.diff(velocity, axis=0) / dt
    assert np.percentile(np.linalg.norm(fd_acceleration, axis=1), 99) <= a_max * 1.05
    # Scalar and vector sampling agree.
    for k in (0, len(t) // 3, len(t) - 1):
        for got, want in zip(
            route.sample(t[k]), (position[k], velocity[k], acceleration[k]), strict=True
        ):
            np.testing.assert_allclose(got, want)


def test_sealed_room_goal_is_unreachable_with_the_nearest_reachable_point(scene_maps):
    scene = scene_maps["sealed_room"]
    with pytest.raises(PlanningError) as caught:
        plan_path(scene.flight_map, scene.start, scene.goal, RADIUS)
    error = caught.value
    assert error.reason == Reason.UNREACHABLE == "unreachable"
    assert "not connected" in str(error)
    # The nearest point is just outside the sealed box (x from 3.2), and a route reaches it.
    assert error.nearest is not None
    assert 3.2 - RADIUS - 0.2 <= error.nearest[0] <= 3.2 - RADIUS
    route = plan_path(scene.flight_map, scene.start, error.nearest, RADIUS)
    check_route_keeps_radius(
        scenes.Scene(scene.name, scene.flight_map, scene.boxes, scene.start, error.nearest), route
    )


def test_goal_inside_a_wall_is_blocked_with_a_sensible_nearest_point(scene_maps):
    scene = scene_maps["room_with_door"]
    in_wall = np.array([2.0, 0.6, 1.2])  # middle of the dividing wall
    with pytest.raises(PlanningError) as caught:
        plan_path(scene.flight_map, scene.start, in_wall, RADIUS)
    error = caught.value
    assert error.reason == "goal_blocked"
    assert error.nearest is not None
    assert error.nearest[0] < 1.9 - RADIUS  # on the start's side of the wall
    assert np.linalg.norm(error.nearest - in_wall) < 0.1 + RADIUS + 0.2
    plan_path(scene.flight_map, scene.start, error.nearest, RADIUS)  # reachable


def test_start_blocked_outside_map_and_not_finite(scene_maps):
    m = scene_maps["room_with_door"].flight_map
    free = np.array([1.0, 0.6, 1.2])
    cases = [
        (np.array([2.0, 0.6, 1.2]), free, "start_blocked"),
        (np.array([1.0, 0.05, 1.2]), free, "start_blocked"),  # closer than the radius to a wall
        (free, np.array([9.0, 0.6, 1.2]), "outside_map"),
        (np.array([-3.0, 0.6, 1.2]), free, "outside_map"),
        (np.array([np.nan, 0.6, 1.2]), free, "not_finite"),
        (free, np.array([1.0, np.inf, 1.2]), "not_finite"),
    ]
    for start, goal, reason in cases:
        with pytest.raises(PlanningError) as caught:
            plan_path(m, start, goal, RADIUS)
        assert caught.value.reason == reason, (start, goal)
    with pytest.raises(PlanningError) as caught:
        plan_path(m, np.array([2.0, 0.6, 1.2]), free, RADIUS)
    assert m.distance(caught.value.nearest) >= RADIUS  # somewhere to put the drone instead


def test_unknown_space_blocks_routes_unless_configured():
    # A room whose far half (x > 2) was never observed.
    boxes = [
        (np.array([-0.1, -0.1, -0.1]), np.array([4.1, 3.1, 0.0])),
        (np.array([-0.1, -0.1, 2.4]), np.array([4.1, 3.1, 2.5])),
    ]
    base = FlightMap.from_boxes([-0.1, -0.1, -0.1], [4.1, 3.1, 2.5], boxes, 0.05)
    observed = np.ones(base.shape, bool)
    observed[int(2.1 / 0.05) :] = False
    start, goal = np.array([1.0, 1.5, 1.2]), np.array([3.0, 1.5, 1.2])
    for unknown_is_free in (False, True):
        m = FlightMap(0.05, unknown_is_free)
        m.update(base.origin, base.blocked, observed)
        if unknown_is_free:
            assert plan_path(m, start, goal, RADIUS).length_m == pytest.approx(2.0, abs=1e-6)
        else:
            with pytest.raises(PlanningError) as caught:
                plan_path(m, start, goal, RADIUS)
            assert caught.value.reason == "goal_blocked"
            assert caught.value.nearest[0] <= 2.0 - RADIUS


def test_route_is_clear_until_the_map_puts_something_on_it(scene_maps):
    scene = scenes.box_in_the_way()  # its own map: this test updates it
    m = scene.flight_map
    route = plan_path(m, scene.start, scene.goal, RADIUS)
    assert route_is_clear(m, route, RADIUS)
    # A new box where the route is a third of the way along.
    middle = route.sample(route.duration_s / 3)[0]
    occupied = m.blocked.copy()
    cell = np.floor((middle - m.origin) / m.voxel_m).astype(int)
    occupied[tuple(slice(c - 2, c + 3) for c in cell)] = True
    changed = m.update(m.origin, occupied, np.ones_like(occupied))
    assert changed is not None and changed.contains(middle)[0]
    assert not route_is_clear(m, route, RADIUS)
    assert route_is_clear(m, route, RADIUS, from_time_s=0.8 * route.duration_s)  # passed it
    replanned = plan_path(m, scene.start, scene.goal, RADIUS)
    assert route_is_clear(m, replanned, RADIUS)
    assert m.distance(dense(replanned.path)).min() >= RADIUS


def test_route_to_where_it_starts_is_a_single_point(scene_maps):
    scene = scene_maps["corridor"]
    route = plan_path(scene.flight_map, scene.start, scene.start, RADIUS)
    assert route.length_m == 0 and route.duration_s == 0
    position, velocity, _ = route.sample(1.0)
    np.testing.assert_allclose(position, scene.start)
    np.testing.assert_allclose(velocity, 0)


def test_a_narrow_door_is_found_on_the_map_own_cells():
    # Door centre clearance 0.225 m; the 10 cm lattice's nodes beside the centre have 0.175 m,
    # too little for their moves, so only the 5 cm cells get through.
    scene = scenes.room_with_door(door_y=(0.8, 1.25))
    route = plan_path(scene.flight_map, scene.start, scene.goal, RADIUS)
    check_route_keeps_radius(scene, route)
    with pytest.raises(PlanningError) as caught:  # a radius that does not fit through
        plan_path(scene.flight_map, scene.start, scene.goal, 0.22)
    assert caught.value.reason == "unreachable"
    assert caught.value.nearest[0] < 1.9


def test_a_route_shorter_than_one_path_step_takes_a_short_time():
    scene = scenes.box_in_the_way()
    for d in (1e-6, 1e-3, 0.01, 0.03):
        goal = scene.start + [d, 0.0, 0.0]
        route = plan_path(scene.flight_map, scene.start, goal, 0.17)
        assert 0 < route.duration_s < 1.0, (d, route.duration_s)
        np.testing.assert_allclose(route.sample(route.duration_s)[0], goal, atol=1e-9)
