"""A session's mesh downloads, world and upright (PLY z up, GLB y up), from a real server on
loopback: a closed session made on disk with a known map and a known gravity."""

from __future__ import annotations

import asyncio
import json

import httpx
import numpy as np
import pytest
from scipy.spatial import cKDTree

from server.datasets import open_dataset
from server.mapping.mesh_files import R_GLTF_UPRIGHT, read_ply
from server.mapping.tsdf import TSDFMap
from server.mapping.upright import upright_rotation
from server.sessions.store import hash_token
from tests.conftest import Stream, auth
from tests.support.glb import accessor, read_glb

SID, TOKEN = "00112233445566aa", "mesh-test-token"
GRAVITY = np.array([0.3, 0.9, -0.3]) / np.linalg.norm([0.3, 0.9, -0.3])  # a tilted phone's


def same_points(a: np.ndarray, b: np.ndarray, tol: float = 1e-5) -> None:
    """The same vertices in any order (marching cubes visits a loaded map's blocks in its hash
    map's order, which differs between loads)."""
    assert a.shape == b.shape
    assert cKDTree(b).query(a)[0].max() < tol and cKDTree(a).query(b)[0].max() < tol


@pytest.fixture
def closed_session(shared_data, tmp_path):
    """(data_dir, the map's world-frame mesh): one frame of synthetic_room0 fused 4 times at
    the identity (enough observations for the map's min_weight), saved as a closed session
    whose first hello said GRAVITY."""
    data_dir = tmp_path / "data"
    folder = data_dir / "sessions" / SID
    folder.mkdir(parents=True)
    ds = open_dataset(shared_data / "synthetic_room0")
    frame = ds[0]
    tsdf = TSDFMap()
    for _ in range(4):
        tsdf.integrate(frame.colour, frame.depth, ds.intrinsics, np.eye(4))
    tsdf.save(folder / "map.npz")
    status = {"id": SID, "closed": True, "gravity": GRAVITY.tolist()}
    meta = {"id": SID, "token_sha256": hash_token(TOKEN), "closed": True, "status": status}
    (folder / "meta.json").write_text(json.dumps(meta))
    return data_dir, TSDFMap.load(folder / "map.npz").mesh()


def test_mesh_downloads_world_upright_and_glb(live_server, closed_session):
    data_dir, world_mesh = closed_session
    server = live_server(data_dir)
    base = f"{server.url}/api/sessions/{SID}"
    world = np.asarray(world_mesh.vertices)
    R = upright_rotation(-GRAVITY, [0, 0, 1])  # the drone's flight frame, too

    r = httpx.get(f"{base}/mesh.ply", headers=auth(TOKEN), timeout=60)
    assert r.status_code == 200
    same_points(np.asarray(read_ply(r.content).vertices), world)

    r = httpx.get(f"{base}/mesh.ply?frame=upright", headers=auth(TOKEN), timeout=60)
    assert r.status_code == 200 and r.headers["content-type"] == "application/octet-stream"
    upright = read_ply(r.content)
    same_points(np.asarray(upright.vertices), world @ R.T)
    assert upright.has_vertex_colors() and len(upright.triangles) == len(world_mesh.triangles)

    r = httpx.get(f"{base}/mesh.glb", headers=auth(TOKEN), timeout=60)
    assert r.status_code == 200 and r.headers["content-type"] == "model/gltf-binary"
    assert 'filename="00112233445566aa-mesh.glb"' in r.headers["content-disposition"]
    document, blob = read_glb(r.content)
    primitive = document["meshes"][0]["primitives"][0]
    y_up = accessor(document, blob, primitive["attributes"]["POSITION"])
    same_points(y_up, world @ (R_GLTF_UPRIGHT @ R).T)  # glTF y: the height against gravity
    assert len(accessor(document, blob, primitive["indices"])) == 3 * len(world_mesh.triangles)

    assert httpx.get(f"{base}/mesh.ply?frame=sideways", headers=auth(TOKEN)).status_code == 422
    assert httpx.get(f"{base}/mesh.glb").status_code == 401
    assert httpx.get(f"{base}/mesh.glb", headers=auth("wrong")).status_code == 404


def test_a_session_without_gravity_is_made_upright_from_its_map(live_server, closed_session):
    data_dir, world_mesh = closed_session
    meta_path = data_dir / "sessions" / SID / "meta.json"
    meta = json.loads(meta_path.read_text())
    meta["status"]["gravity"] = None
    meta_path.write_text(json.dumps(meta))
    server = live_server(data_dir)
    r = httpx.get(f"{server.url}/api/sessions/{SID}/mesh.ply?frame=upright", headers=auth(TOKEN))
    assert r.status_code == 200
    upright = read_ply(r.content)
    vertices, triangles = np.asarray(upright.vertices), np.asarray(upright.triangles)
    # A rotation of the world mesh about the origin.
    distances = np.linalg.norm(np.asarray(world_mesh.vertices), axis=1)
    np.testing.assert_allclose(
        np.sort(np.linalg.norm(vertices, axis=1)), np.sort(distances), atol=1e-5
    )
    assert len(triangles) == len(world_mesh.triangles)
    # (How well up is found from a map: tests/unit/mapping/test_upright.py.)


def test_a_live_maps_chunks_say_when_its_mesh_can_be_downloaded(live_server, shared_data):
    """map_chunk.surface is false while mesh.ply answers 409 and true from the chunk on after
    which it answers with a mesh (the page asks for the mesh only then: no 409 in its console)."""
    server = live_server()
    sid, token = server.create_session()
    s = Stream(server.ws_url, sid, token, open_dataset(shared_data / "synthetic_room0"))
    mesh_url = f"{server.url}/api/sessions/{sid}/mesh.ply"

    def get() -> httpx.Response:
        return httpx.get(mesh_url, headers=auth(token), timeout=60)

    async def go() -> tuple[httpx.Response, httpx.Response]:
        await s.open()
        await s.send(0)
        early = await asyncio.to_thread(get)
        seq = 1
        while True not in s.surfaces and seq < 60:
            await s.send(seq, index=2 * seq)
            seq += 1
        said = await asyncio.to_thread(get)  # the session still live
        await s.close()
        return early, said

    early, said = asyncio.run(go())
    assert early.status_code == 409
    assert early.json()["error"]["message"] == "the map has no surface yet", early.text
    assert s.surfaces[0] is False and True in s.surfaces, s.surfaces
    first = s.surfaces.index(True)
    assert s.surfaces[first:] == [True] * (len(s.surfaces) - first), s.surfaces
    assert said.status_code == 200 and len(read_ply(said.content).triangles) > 0
