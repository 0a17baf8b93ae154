"""Mesh files that other tools open upright: PLY with z up, binary glTF (GLB) with y up.

Both take a mesh in the world frame and ``R_upright_world`` (server/mapping/upright.py) and
rotate it about the world origin, so positions stay in metres and the first camera stays at
the origin. PLY has no stated up axis; Blender, MeshLab and ROS take z as up, so the PLY is
written in the upright frame itself (x forward, y left, z up). glTF 2.0 states its own: +y up,
+z forward, -x right, so the GLB is the upright frame with its axes renamed (glTF x = upright
y, glTF y = upright z, glTF z = upright x); Blender's glTF importer turns it z up again.

Open3D writes .glb too, but with the buffer as a base64 URI inside the JSON (a third larger)
and, for meshes over 65 535 vertices, one that its own reader rejects as out of range; so the
GLB is written here: one JSON chunk, one BIN chunk, float32 positions, normals and linear
colours, uint32 indices.
"""

from __future__ import annotations

import json
import struct
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import open3d as o3d
from numpy.typing import ArrayLike

from server import __version__
from server.atomic import atomic_write, atomic_write_bytes
from server.errors import DroneSimError
from server.geometry.arrays import FloatArray

# glTF axes from upright axes: x = upright y (left), y = upright z (up), z = upright x (forward).
R_GLTF_UPRIGHT = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
GLB_MAGIC, GLB_VERSION = b"glTF", 2
CHUNK_JSON, CHUNK_BIN = b"JSON", b"BIN\x00"
_FLOAT, _UINT32 = 5126, 5125  # glTF componentType
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963  # bufferView targets
_TRIANGLES = 4  # primitive mode


class MeshFileError(DroneSimError):
    """A mesh that cannot be written: no triangles, or arrays of the wrong shape."""


def rotated(mesh: o3d.geometry.TriangleMesh, R: ArrayLike) -> o3d.geometry.TriangleMesh:
    """A copy of ``mesh`` rotated by R (3x3) about the origin (normals too)."""
    out = o3d.geometry.TriangleMesh(mesh)
    out.rotate(np.asarray(R, dtype=np.float64), center=np.zeros(3))
    return out


def write_ply(path: str | Path, mesh: o3d.geometry.TriangleMesh) -> None:
    """``mesh`` as binary PLY (vertex positions, normals and colours; faces), atomically."""
    if not mesh.has_triangles():
        raise MeshFileError(f"the mesh has no triangles to write to {path}")

    def write(tmp: str) -> None:
        if not o3d.io.write_triangle_mesh(Path(tmp), mesh):
            raise MeshFileError(f"Open3D could not write {path}")

    atomic_write(path, write, suffix=".ply", mode=0o644)


def ply_bytes(mesh: o3d.geometry.TriangleMesh) -> bytes:
    """``mesh`` as the bytes of a binary PLY file."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "mesh.ply"
        write_ply(path, mesh)
        return path.read_bytes()


def read_ply(data: bytes) -> o3d.geometry.TriangleMesh:
    """A triangle mesh from the bytes of a PLY file."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "mesh.ply"
        path.write_bytes(data)
        return o3d.io.read_triangle_mesh(path)


def srgb_to_linear(c: ArrayLike) -> FloatArray:
    """sRGB colour values (0..1, as images and Open3D hold them) to linear ones (0..1, as
    glTF's COLOR_0 is defined)."""
    c = np.clip(np.asarray(c, dtype=np.float64), 0.0, 1.0)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def glb_bytes(
    positions: ArrayLike,
    triangles: ArrayLike,
    normals: ArrayLike | None = None,
    colours_linear: ArrayLike | None = None,
) -> bytes:
    """A binary glTF 2.0 file holding one triangle mesh, as given (glTF axes, metres).

    positions (N, 3); triangles (M, 3) vertex indices; normals (N, 3) (made unit; zero ones
    become +y); colours_linear (N, 3) 0..1. The material is matte (metallic 0, roughness 1)
    and double-sided: glTF's default material is a metal, which shows a mesh nearly black."""
    p = np.ascontiguousarray(positions, dtype=np.float32).reshape(-1, 3)
    t = np.ascontiguousarray(triangles, dtype=np.uint32).reshape(-1, 3)
    if len(t) == 0:
        raise MeshFileError("the mesh has no triangles")
    if int(t.max()) >= len(p):
        raise MeshFileError(f"a triangle names vertex {int(t.max())} of {len(p)}")
    attributes = {"POSITION": p}
    if normals is not None:
        n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
        length = np.linalg.norm(n, axis=1, keepdims=True)
        n = np.where(length > 1e-12, n / np.maximum(length, 1e-12), [0.0, 1.0, 0.0])
        attributes["NORMAL"] = n.astype(np.float32)
    if colours_linear is not None:
        attributes["COLOR_0"] = np.clip(colours_linear, 0, 1).astype(np.float32).reshape(-1, 3)
    for name, values in attributes.items():
        if values.shape != p.shape:
            raise MeshFileError(f"{name} has shape {values.shape}, positions {p.shape}")

    blob = bytearray()
    views: list[dict[str, int]] = []
    accessors: list[dict[str, Any]] = []

    def add(data: np.ndarray, target: int, accessor: dict[str, Any]) -> int:
        """Append ``data`` as a bufferView (4-byte aligned) and its accessor; its index."""
        views.append(
            {"buffer": 0, "byteOffset": len(blob), "byteLength": data.nbytes, "target": target}
        )
        blob.extend(data.tobytes())
        blob.extend(b"\x00" * (-len(blob) % 4))
        accessors.append({"bufferView": len(views) - 1, **accessor})
        return len(accessors) - 1

    indices = add(
        t.reshape(-1),
        _ELEMENT_ARRAY_BUFFER,
        {"componentType": _UINT32, "count": t.size, "type": "SCALAR"},
    )
    slots = {}
    for name, values in attributes.items():
        accessor = {"componentType": _FLOAT, "count": len(values), "type": "VEC3"}
        if name == "POSITION":  # required by the spec for positions
            accessor |= {"min": p.min(axis=0).tolist(), "max": p.max(axis=0).tolist()}
        slots[name] = add(values, _ARRAY_BUFFER, accessor)
    document = {
        "asset": {"version": "2.0", "generator": f"dronesim-ar {__version__}"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "name": "map"}],
        "meshes": [
            {
                "name": "map",
                "primitives": [
                    {"attributes": slots, "indices": indices, "mode": _TRIANGLES, "material": 0}
                ],
            }
        ],
        "materials": [
            {
                "name": "map",
                "doubleSided": True,
                "pbrMetallicRoughness": {"metallicFactor": 0.0, "roughnessFactor": 1.0},
            }
        ],
        "buffers": [{"byteLength": len(blob)}],
        "bufferViews": views,
        "accessors": accessors,
    }
    text = json.dumps(document, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)  # the JSON chunk is padded with spaces, the BIN with zeros
    total = 12 + 8 + len(text) + 8 + len(blob)
    return b"".join(
        [
            struct.pack("<4sII", GLB_MAGIC, GLB_VERSION, total),
            struct.pack("<I4s", len(text), CHUNK_JSON),
            text,
            struct.pack("<I4s", len(blob), CHUNK_BIN),
            bytes(blob),
        ]
    )


def upright_glb(mesh_upright: o3d.geometry.TriangleMesh) -> bytes:
    """A mesh in the upright frame (z up) as GLB bytes (y up, glTF's axes)."""
    if not mesh_upright.has_triangles():
        raise MeshFileError("the mesh has no triangles")
    to_gltf = R_GLTF_UPRIGHT.T  # row vectors: p_gltf = R_GLTF_UPRIGHT @ p
    normals = np.asarray(mesh_upright.vertex_normals) @ to_gltf
    colours = np.asarray(mesh_upright.vertex_colors)
    return glb_bytes(
        np.asarray(mesh_upright.vertices) @ to_gltf,
        np.asarray(mesh_upright.triangles),
        normals if mesh_upright.has_vertex_normals() else None,
        srgb_to_linear(colours) if mesh_upright.has_vertex_colors() else None,
    )


def write_upright(
    folder: str | Path, mesh_world: o3d.geometry.TriangleMesh, R_upright_world: ArrayLike
) -> dict[str, Path]:
    """``mesh.ply`` (z up) and ``mesh.glb`` (y up) of ``mesh_world`` in ``folder``; their paths."""
    folder = Path(folder)
    mesh = rotated(mesh_world, R_upright_world)
    paths = {"mesh": folder / "mesh.ply", "glb": folder / "mesh.glb"}
    write_ply(paths["mesh"], mesh)
    atomic_write_bytes(paths["glb"], upright_glb(mesh), mode=0o644)
    return paths
