"""Upright meshes: up found from gravity or from a map's floors, and the PLY (z up) and GLB (y up)
files written from it, read back."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
from scipy.spatial.transform import Rotation

from server.mapping.mesh_files import (
    R_GLTF_UPRIGHT,
    MeshFileError,
    glb_bytes,
    srgb_to_linear,
    upright_glb,
    write_upright,
)
from server.mapping.upright import (
    UpSource,
    triangle_normals,
    up_from_surfaces,
    upright_frame,
    upright_rotation,
)
from tests.support.glb import accessor, read_glb

Y_DOWN = np.array([0.0, 1.0, 0.0])  # a level camera's gravity, in its own axes


def grid(size_m: float, n: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """A square (size_m x size_m) in the plane z = 0 centred on the origin, normal +z."""
    u = np.linspace(-size_m / 2, size_m / 2, n + 1)
    x, y = np.meshgrid(u, u)
    vertices = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)
    i = np.arange(n)[:, None] * (n + 1) + np.arange(n)[None, :]
    a, b, c, d = i.ravel(), i.ravel() + 1, i.ravel() + n + 1, i.ravel() + n + 2
    triangles = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    return vertices, triangles


def placed(part: tuple[np.ndarray, np.ndarray], R: np.ndarray, t) -> tuple:
    return part[0] @ R.T + np.asarray(t, float), part[1]


def joined(*parts: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    vertices, triangles, offset = [], [], 0
    for v, t in parts:
        vertices.append(v)
        triangles.append(t + offset)
        offset += len(v)
    return np.concatenate(vertices), np.concatenate(triangles)


def room_in_camera_axes() -> tuple[np.ndarray, np.ndarray]:
    """A room seen by a level camera at the origin (x right, y down, z forward): a 4 x 4 m
    floor 1.4 m below it (normal up, -y), a wall 2 m ahead facing it, a sloped 1 m^2 ramp
    (30 degrees) and a ceiling 1.2 m above facing down: a floor must win over all of them."""
    to_camera = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # a z-up part into y-down axes
    floor = placed(grid(4.0), to_camera, [0, 1.4, 2])
    wall = placed(grid(4.0), to_camera @ Rotation.from_euler("x", 90, degrees=True).as_matrix(),
                  [0, 0, 2.0])  # fmt: skip
    wall = (wall[0], wall[1][:, ::-1])  # wound to face the camera (-z)
    ramp_R = to_camera @ Rotation.from_euler("x", 30, degrees=True).as_matrix()
    ramp = placed(grid(1.0), ramp_R, [1, 1.0, 1])
    ceiling = placed(grid(4.0), to_camera, [0, -1.2, 2])
    ceiling = (ceiling[0], ceiling[1][:, ::-1])  # seen from below: its normal points down
    return joined(floor, wall, ramp, ceiling)


def angle_deg(a, b) -> float:
    a, b = np.asarray(a, float), np.asarray(b, float)
    cos = a @ b / np.linalg.norm(a) / np.linalg.norm(b)
    return float(np.degrees(np.arccos(np.clip(cos, -1, 1))))


# ---- up -----------------------------------------------------------------------------------------


def test_the_upright_rotation_puts_up_on_z_and_forward_on_x():
    up, forward = np.array([0.1, -1.0, 0.2]), np.array([0.0, 0.3, 1.0])
    R = upright_rotation(up, forward)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(R @ (up / np.linalg.norm(up)), [0, 0, 1], atol=1e-12)
    assert (R @ forward)[1] == pytest.approx(0.0, abs=1e-12) and (R @ forward)[0] > 0
    # A camera looking straight down has no level forward: its x axis is levelled instead.
    R = upright_rotation([0, -1, 0], [0, -1, 0])
    np.testing.assert_allclose(R @ [0, -1, 0], [0, 0, 1], atol=1e-12)


def test_triangle_normals_follow_the_winding_and_give_areas():
    normals, areas = triangle_normals(*grid(2.0, n=4))
    np.testing.assert_allclose(normals, np.tile([0, 0, 1.0], (32, 1)), atol=1e-12)
    assert areas.sum() == pytest.approx(4.0)


@pytest.mark.parametrize("tilt_deg", [0.0, 15.0, 40.0])
def test_a_tilted_floor_comes_out_with_z_up(tilt_deg):
    """A camera pitched down by tilt_deg at the room: up is found from the floor within a
    degree, and the upright frame maps the floor's normal to +z."""
    vertices, triangles = room_in_camera_axes()
    pitch = Rotation.from_euler("x", -tilt_deg, degrees=True).as_matrix()  # camera <- level
    rng = np.random.default_rng(1)
    R_world_camera = Rotation.random(random_state=rng).as_matrix()  # any world frame at all
    world = (vertices @ pitch.T) @ R_world_camera.T
    true_up = R_world_camera @ pitch @ np.array([0.0, -1.0, 0.0])
    T_world_camera0 = np.eye(4)
    T_world_camera0[:3, :3] = R_world_camera
    R, source = upright_frame(T_world_camera0, world, triangles)
    assert source is UpSource.SURFACES
    assert angle_deg(R[2], true_up) < 1.0
    floor_normal = triangle_normals(world, triangles)[0][0]
    assert angle_deg(R @ floor_normal, [0, 0, 1]) < 1.0
    # Upright x: the camera's forward made level.
    forward = R @ R_world_camera @ [0, 0, 1.0]
    assert abs(forward[1]) < 1e-9 and forward[0] > 0


def test_up_from_a_real_maps_surfaces_is_nearer_the_truth_than_the_camera(shared_data):
    """synthetic_room0's first frame, fused at the identity: its ground truth's world is z up,
    16 degrees from the camera's -y; up from the map's surfaces comes within 6."""
    from server.datasets import open_dataset
    from server.mapping.tsdf import TSDFMap

    ds = open_dataset(shared_data / "synthetic_room0")
    frame = ds[0]
    tsdf = TSDFMap()
    for _ in range(4):  # the map's min_weight
        tsdf.integrate(frame.colour, frame.depth, ds.intrinsics, np.eye(4))
    mesh = tsdf.mesh()
    true_up = ds.ground_truth.poses[0][:3, :3].T @ [0, 0, 1.0]  # world z, in the camera
    assert angle_deg(true_up, [0, -1, 0]) > 15
    R, source = upright_frame(np.eye(4), np.asarray(mesh.vertices), np.asarray(mesh.triangles))
    assert source is UpSource.SURFACES and angle_deg(R[2], true_up) < 6.0


def test_gravity_wins_and_the_camera_is_the_last_resort():
    vertices, triangles = room_in_camera_axes()
    g = np.array([0.2, 1.0, -0.1])
    R, source = upright_frame(np.eye(4), vertices, triangles, gravity_world=g)
    assert source is UpSource.GRAVITY and angle_deg(R[2], -g) < 1e-9
    wall_only = (vertices[121:242] - vertices[121:242].mean(0), triangles[:200])
    R, source = upright_frame(np.eye(4), *wall_only)
    assert source is UpSource.CAMERA and angle_deg(R[2], [0, -1, 0]) < 1e-9
    R, source = upright_frame(np.eye(4))
    assert source is UpSource.CAMERA


def test_a_small_or_far_tilted_surface_is_not_a_floor():
    small = grid(0.2)  # 0.04 m^2: below the area needed
    assert up_from_surfaces(*small, prior_up=[0, 0, 1]) is None
    steep = placed(grid(4.0), Rotation.from_euler("x", 60, degrees=True).as_matrix(), [0, 0, 0])
    assert up_from_surfaces(*steep, prior_up=[0, 0, 1]) is None  # 60 degrees: a wall or a ramp


# ---- files --------------------------------------------------------------------------------------


def coloured_box() -> o3d.geometry.TriangleMesh:
    """A 1 x 2 x 3 m box (x, y, z), normals and colours on, in a camera's axes (y down)."""
    mesh = o3d.geometry.TriangleMesh.create_box(1.0, 2.0, 3.0)
    mesh.compute_vertex_normals()
    mesh.vertex_colors = o3d.utility.Vector3dVector(np.linspace(0, 1, 24).reshape(8, 3))
    return mesh


def test_the_glb_holds_the_mesh_y_up_in_one_binary_chunk():
    box = coloured_box()
    R = upright_rotation([0, -1, 0], [0, 0, 1])  # a level camera: up is -y
    upright = o3d.geometry.TriangleMesh(box).rotate(R, center=np.zeros(3))
    document, blob = read_glb(upright_glb(upright))
    assert document["asset"]["version"] == "2.0"
    primitive = document["meshes"][0]["primitives"][0]
    assert primitive["mode"] == 4
    attributes = primitive["attributes"]
    positions = accessor(document, blob, attributes["POSITION"])
    indices = accessor(document, blob, primitive["indices"])
    assert positions.shape == (8, 3) and indices.shape == (36,)
    np.testing.assert_array_equal(indices.reshape(-1, 3), np.asarray(box.triangles))
    # glTF is y up: the box's 2 m along the camera's y (down) is now its height along +y,
    # below the camera's origin; its 3 m depth (camera z, forward) lies along glTF +z.
    world = np.asarray(box.vertices)
    np.testing.assert_allclose(positions, world @ (R_GLTF_UPRIGHT @ R).T, atol=1e-6)
    assert positions[:, 1].min() == pytest.approx(-2.0) and positions[:, 1].max() == 0.0
    assert positions[:, 2].max() == pytest.approx(3.0)
    a = document["accessors"][attributes["POSITION"]]
    np.testing.assert_allclose(a["min"], positions.min(0))
    np.testing.assert_allclose(a["max"], positions.max(0))
    normals = accessor(document, blob, attributes["NORMAL"])
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-6)
    colours = accessor(document, blob, attributes["COLOR_0"])
    np.testing.assert_allclose(colours, srgb_to_linear(np.asarray(box.vertex_colors)), atol=1e-6)
    material = document["materials"][primitive["material"]]
    assert material["pbrMetallicRoughness"]["metallicFactor"] == 0.0


def test_a_glb_of_nothing_or_of_bad_indices_is_refused():
    with pytest.raises(MeshFileError, match="no triangles"):
        glb_bytes(np.zeros((3, 3)), np.zeros((0, 3)))
    with pytest.raises(MeshFileError, match="vertex 3 of 3"):
        glb_bytes(np.zeros((3, 3)), [[0, 1, 3]])


def test_write_upright_gives_a_z_up_ply_and_the_same_mesh_as_glb(tmp_path):
    box = coloured_box()
    R = upright_rotation([0, -1, 0], [0, 0, 1])
    paths = write_upright(tmp_path, box, R)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mesh.glb", "mesh.ply"]
    ply = o3d.io.read_triangle_mesh(str(paths["mesh"]))
    z_up = np.asarray(ply.vertices)
    np.testing.assert_allclose(z_up, np.asarray(box.vertices) @ R.T, atol=1e-6)
    assert z_up[:, 2].min() == pytest.approx(-2.0) and z_up[:, 2].max() == pytest.approx(0.0)
    assert ply.has_vertex_colors() and len(ply.triangles) == 12
    document, blob = read_glb(paths["glb"].read_bytes())
    positions = accessor(
        document, blob, document["meshes"][0]["primitives"][0]["attributes"]["POSITION"]
    )
    np.testing.assert_allclose(positions, z_up[:, [1, 2, 0]], atol=1e-6)  # glTF x, y, z
