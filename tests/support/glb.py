"""GLB files read back: the JSON document and binary chunk, their framing checked, and an
accessor's values (the upright meshes' tests and the mesh downloads' alike)."""

from __future__ import annotations

import json
import struct

import numpy as np


def read_glb(data: bytes) -> tuple[dict, bytes]:
    """The JSON document and BIN chunk of a GLB file, its framing checked."""
    magic, version, length = struct.unpack_from("<4sII", data, 0)
    assert (magic, version, length) == (b"glTF", 2, len(data))
    json_len, json_type = struct.unpack_from("<I4s", data, 12)
    assert json_type == b"JSON" and json_len % 4 == 0
    document = json.loads(data[20 : 20 + json_len])
    bin_len, bin_type = struct.unpack_from("<I4s", data, 20 + json_len)
    assert bin_type == b"BIN\x00" and bin_len % 4 == 0
    blob = data[28 + json_len : 28 + json_len + bin_len]
    assert len(blob) == bin_len == document["buffers"][0]["byteLength"]
    assert 28 + json_len + bin_len == len(data)
    return document, blob


def accessor(document: dict, blob: bytes, index: int) -> np.ndarray:
    a = document["accessors"][index]
    view = document["bufferViews"][a["bufferView"]]
    assert view["byteOffset"] % 4 == 0
    dtype = {5126: np.float32, 5125: np.uint32}[a["componentType"]]
    width = {"SCALAR": 1, "VEC3": 3}[a["type"]]
    values = np.frombuffer(
        blob, dtype, a["count"] * width, view["byteOffset"] + a.get("byteOffset", 0)
    )
    assert values.nbytes <= view["byteLength"]
    return values.reshape(a["count"], width) if width > 1 else values
