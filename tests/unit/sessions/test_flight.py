"""The session's drone (server.sessions.runtime.flight): frames, tapped pixels, commands,
spawning."""

from __future__ import annotations

import numpy as np
import pytest

from server.geometry import Intrinsics, exp_se3
from server.sessions.errors import CommandRefused
from server.sessions.runtime.flight import Flight
from server.sessions.runtime.flight_view import flight_frame
from server.sessions.updates import DroneNotice, DroneUpdate
from server.simulation import scenes
from server.simulation.config import SimulationConfig

K = Intrinsics(500.0, 500.0, 319.5, 239.5, 640, 480)


def test_flight_frame_puts_up_against_gravity_and_x_along_the_view():
    R = flight_frame(None)  # camera upright and level: gravity is +y
    np.testing.assert_allclose(R @ [0, -1, 0], [0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(R @ [0, 0, 1], [1, 0, 0], atol=1e-12)
    rng = np.random.default_rng(3)
    for _ in range(20):
        g = rng.normal(size=3) * rng.uniform(0.1, 10)
        R = flight_frame(g)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0)
        np.testing.assert_allclose(R @ (-g / np.linalg.norm(g)), [0, 0, 1], atol=1e-12)
    R = flight_frame([0.0, 0.0, 1.0])  # looking straight down: still a valid frame
    np.testing.assert_allclose(R @ [0, 0, -1], [0, 0, 1], atol=1e-12)


def make_flight(gravity=None, published=None) -> Flight:
    out = [] if published is None else published
    return Flight(SimulationConfig(), K, gravity, out.append, state_hz=50.0)


def _in_the_door_room(flight: Flight):
    """Hand the flight the door scene's grid as the session would (an occupancy grid in the
    flight frame) and a camera frame 0.8 m behind the scene's start, looking along flight +x.
    -> (scene, T_world_camera)."""
    R = flight.R_flight_world
    scene = scenes.room_with_door()
    fm = scene.flight_map
    observed = np.ones(fm.shape, dtype=bool)
    flight.map_changed(fm.origin, fm.blocked & observed, observed)
    T = np.eye(4)
    T[:3, :3] = R.T @ np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]])  # camera axes in flight
    T[:3, 3] = R.T @ (scene.start - [0.8, 0.0, 0.0])
    flight.camera_moved(0, T, np.full((480, 640), 3.0, np.float32))
    return scene, T


def test_a_tapped_pixel_is_the_surface_point_it_shows_standoff_back():
    flight = make_flight()
    T = exp_se3(np.array([0.1, -0.2, 0.05, 0.3, -0.1, 0.5]))
    depth = np.full((480, 640), 2.0, np.float32)  # a wall 2 m ahead
    flight.camera_moved(7, T, depth)
    u, v = 100.0, 400.0
    ray = np.array([(u - K.cx) / K.fx, (v - K.cy) / K.fy, 1.0])
    expected_camera = ray * 2.0 - 0.4 * ray / np.linalg.norm(ray)
    got = flight.frames.pixel_target((u, v), 7)
    np.testing.assert_allclose(got, T[:3, :3] @ expected_camera + T[:3, 3], atol=1e-9)
    np.testing.assert_allclose(flight.frames.pixel_target((u, v), None), got)  # latest frame

    with pytest.raises(CommandRefused, match="not among the last"):
        flight.frames.pixel_target((u, v), 3)
    depth[380:420, 80:120] = 0.0
    flight.camera_moved(8, T, depth)
    with pytest.raises(CommandRefused, match="no depth"):
        flight.frames.pixel_target((u, v), 8)
    with pytest.raises(CommandRefused, match="outside"):
        flight.frames.pixel_target((700.0, 10.0), 8)


def test_commands_before_the_drone_spawns_are_refused_clearly():
    flight = make_flight()
    with pytest.raises(CommandRefused, match="spawned") as info:
        flight.command("goto", 1, target=[1.0, 0.0, 0.0])
    assert info.value.code == "bad_command"
    flight.command("sticks", 2, sticks=[0.0, 0.0, 0.0, 0.0])  # sticks are ignored, not refused


def test_with_a_tilted_phone_the_drone_flies_level_and_reports_in_the_world_frame():
    """The phone's first frame is rolled and pitched; the drone's map and physics are in the
    gravity frame, everything it reports in the world (first camera) frame."""
    gravity = np.array([0.3, 0.9, 0.2])
    published = []
    flight = make_flight(gravity, published)
    R = flight.R_flight_world
    scene, T = _in_the_door_room(flight)
    fm = scene.flight_map
    for _ in range(3):
        flight._tick(0.02)
    assert flight.spawned
    goal_world = R.T @ scene.goal
    flight.command("goto", 5, target=goal_world)
    for _ in range(int(15 / 0.02)):
        notices = flight._tick(0.02)
        published += notices
        if any(n.event == "arrived" for n in notices):
            break
    events = [n.event for n in published if isinstance(n, DroneNotice)]
    assert "arrived" in events and "collision" not in events
    # The message names the target in the world frame, as the event's fields and the goto do
    # (it once printed the flight frame's coordinates).
    arrived = next(n for n in published if isinstance(n, DroneNotice) and n.event == "arrived")
    assert "({:.2f}, {:.2f}, {:.2f}) m".format(*goal_world) in arrived.message, arrived.message
    assert "({:.2f}, {:.2f}, {:.2f}) m".format(*scene.goal) not in arrived.message
    state = flight.state()
    assert isinstance(state, DroneUpdate) and state.mode == "hover"
    assert np.linalg.norm(state.T_world_drone[:3, 3] - goal_world) < 0.15
    # Level flight: the drone's up is the world's up (against gravity).
    up_world = -gravity / np.linalg.norm(gravity)
    assert state.T_world_drone[:3, :3] @ [0, 0, 1] @ up_world > 0.99
    np.testing.assert_allclose(
        state.T_camera_drone, np.linalg.inv(T) @ state.T_world_drone, atol=1e-9
    )

    # A goal inside the door's wall is refused with a reachable point nearby, in world terms.
    in_wall = R.T @ np.array([2.0, 0.5, 1.0])
    with pytest.raises(CommandRefused) as info:
        flight.command("goto", 6, target=in_wall)
    assert info.value.code == "unreachable_target"
    message = str(info.value)  # in the world frame the client knows, with the reason in words
    assert "({:.2f}, {:.2f}, {:.2f}) m".format(*in_wall) in message and "obstacle" in message
    assert info.value.nearest is not None  # the free side of the wall
    assert fm.distance((R @ info.value.nearest)[None])[0] >= SimulationConfig().radius_m


class _FakeMap:
    """Stands in for a TSDFMap: hands out the queued sub-boxes, records how it was asked."""

    def __init__(self, boxes):
        self.boxes, self.asked = list(boxes), []

    def occupancy_update(self, voxel_m, R_grid_world):
        self.asked.append((voxel_m, R_grid_world))
        return self.boxes.pop(0) if self.boxes else None


def test_sub_boxes_fed_between_ticks_merge_and_spawn_the_drone():
    """feed_from_map after every fused frame: boxes pending together merge (none overwrites
    another) and the flight thread applies them at once."""
    flight = make_flight()
    scene = scenes.room_with_door()
    fm = scene.flight_map
    observed = np.ones(fm.shape, dtype=bool)
    blocked = fm.blocked.copy()
    half = fm.shape[0] // 2
    v = fm.voxel_m
    # The room in two halves, the second overlapping the first by two cells, then a wall
    # block in the first half (overwriting those cells).
    boxes = [
        (fm.origin, blocked[:half], observed[:half]),
        (fm.origin + [(half - 2) * v, 0, 0], blocked[half - 2 :], observed[half - 2 :]),
        (fm.origin + np.array([4, 10, 4]) * v, np.ones((3, 3, 3), bool), np.ones((3, 3, 3), bool)),
    ]
    source = _FakeMap(boxes)
    for _ in boxes:
        assert flight.feed_from_map(source)
    assert not flight.feed_from_map(source)  # nothing new
    assert source.asked[0][0] == flight.config.voxel_m
    np.testing.assert_array_equal(source.asked[0][1], flight.R_flight_world)
    T = np.eye(4)
    T[:3, :3] = flight.R_flight_world.T @ np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]])
    T[:3, 3] = flight.R_flight_world.T @ (scene.start - [0.8, 0.0, 0.0])
    flight.camera_moved(0, T, np.full((480, 640), 3.0, np.float32))
    flight._tick(0.02)
    expected = blocked.copy()
    expected[4:7, 10:13, 4:7] = True
    np.testing.assert_array_equal(flight.flight_map.blocked, expected)
    np.testing.assert_allclose(flight.flight_map.origin, fm.origin, atol=1e-12)
    assert flight.spawned
    assert not flight.feed_from_map(object())  # a failure is logged, never raised


def _rotation_about_y(deg: float, t) -> np.ndarray:
    a = np.radians(deg)
    T = np.eye(4)
    T[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
    T[:3, 3] = t
    return T


def test_a_loop_correction_shows_the_drone_in_the_corrected_world_before_its_map_follows():
    """map_corrected goes out at once and poses come in the corrected world, while the drone's
    map is rebuilt seconds later: meanwhile the drone is reported (and targets are read) in the
    corrected world, so it stays where it was relative to the camera; when the rebuilt map
    arrives the drone moves into it and nothing the client sees jumps."""
    flight = make_flight()
    R = flight.R_flight_world
    scene, T = _in_the_door_room(flight)
    fm = scene.flight_map
    observed = np.ones(fm.shape, dtype=bool)
    for _ in range(50):
        flight._tick(0.02)
    before = flight.state()
    assert before is not None and before.mode == "hover"

    # A correction of 3 deg about the world's up (gravity is +y here) and 8 cm.
    C = _rotation_about_y(3.0, [0.05, 0.0, 0.08])
    flight.world_corrected(C)
    flight.camera_moved(1, C @ T, np.full((480, 640), 3.0, np.float32))  # tracked in it
    shown = flight.state()
    np.testing.assert_allclose(shown.T_world_drone, C @ before.T_world_drone, atol=1e-9)
    np.testing.assert_allclose(shown.T_camera_drone, before.T_camera_drone, atol=1e-9)
    np.testing.assert_allclose(shown.velocity, C[:3, :3] @ before.velocity, atol=1e-9)
    # The simulation itself has not moved: it still flies the old map.
    np.testing.assert_allclose(
        flight.sim.status().T_flight_drone,
        np.linalg.inv(flight.T_world_flight) @ before.T_world_drone,
        atol=1e-9,
    )
    # A target named in the corrected world is the same place of the old map to the planner.
    goal_world = R.T @ scene.goal
    flight.command("goto", 5, target=C[:3, :3] @ goal_world + C[:3, 3])
    np.testing.assert_allclose(flight.sim.status().target, scene.goal, atol=1e-9)
    np.testing.assert_allclose(flight.state().target, C[:3, :3] @ goal_world + C[:3, 3], atol=1e-9)
    # A tap on the frame from before the correction is read in its corrected pose.
    np.testing.assert_allclose(
        flight.frames.pixel_target((320.0, 240.0), 0), flight.frames.pixel_target((320.0, 240.0), 1)
    )
    flight.command("hold", 6)
    flight._tick(0.02)
    held = flight.state()

    # The rebuilt map (its content is not what is checked here) and the move into it.
    flight.map_replaced(fm.origin, fm.blocked & observed, observed, C, frames=1)
    flight._tick(0.0)
    after = flight.state()
    assert flight.corrections == 1
    np.testing.assert_allclose(flight.view.T_view_sim, np.eye(4), atol=1e-9)
    np.testing.assert_allclose(after.T_world_drone[:3, 3], held.T_world_drone[:3, 3], atol=1e-6)
    np.testing.assert_allclose(after.T_world_drone[:3, :3], held.T_world_drone[:3, :3], atol=1e-3)
    np.testing.assert_allclose(
        flight.sim.status().T_flight_drone[:3, 3],
        (np.linalg.inv(flight.T_world_flight) @ held.T_world_drone)[:3, 3],
        atol=1e-6,
    )
