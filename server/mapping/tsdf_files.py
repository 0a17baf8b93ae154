"""The TSDF map's file (``TSDFMap.save``/``load``): a zip of numpy arrays, deflated, named
``FILE_FORMAT`` inside. TSDF values are stored as float16 (-1..1: steps of at most 1/2048 of the
truncation) and colours as uint8, about a tenth of the float32 grid (a 600-frame room: 64 MB ->
6 MB). The free-space grid beside it (server/mapping/free_space.py), when the map has one, is
stored the same way under ``free_*`` names (a reader that knows none of them loads the TSDF
alone). Files in the layout of Open3D's own ``VoxelBlockGrid.save`` (an earlier version's) are
read too: ``read_tsdf`` then returns no blocks, for Open3D to load."""

from __future__ import annotations

import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from server.atomic import atomic_write
from server.geometry.arrays import Float32Array, FloatArray

FILE_FORMAT = "dronesim-tsdf-2"


@dataclass
class StoredTSDF:
    """What a TSDF map file holds: voxel size (metres) and block resolution, the fused cameras'
    positions (world (N, 3), metres; None in an old file without them), and the blocks: keys
    (N, 3) block coordinates and values per attribute (N, R, R, R, channels) float32, colour on
    0..255; both None for a file in Open3D's own layout. free_keys and free_values (tsdf and
    weight): the free-space grid's blocks, of voxels free_voxel_m wide (None: none stored)."""

    voxel_m: float
    block_resolution: int
    camera_positions: FloatArray | None
    keys: NDArray[np.int32] | None = None
    values: dict[str, Float32Array] | None = None
    free_voxel_m: float = 0.0
    free_keys: NDArray[np.int32] | None = None
    free_values: dict[str, Float32Array] | None = None


def write_tsdf(path: str | Path, stored: StoredTSDF, compress: bool = True) -> None:
    """Write a map's blocks (keys and values given) to ``path``, atomically, readable by all;
    ``compress``: deflated (a third of the size, ~100 ms more CPU for a room), else stored."""
    assert stored.keys is not None and stored.values is not None
    colour = stored.values["color"]
    # Open3D's grid holds colour on 0..255 (given the 0..1 images integrate makes); should
    # a grid hold 0..1, it is stored scaled up, so that uint8 steps stay fine either way.
    colour_scale = 1.0 if colour.size == 0 or float(colour.max()) > 1.0 + 1e-6 else 1.0 / 255
    arrays = {
        "format": np.array(FILE_FORMAT),
        "key": stored.keys,
        "tsdf": stored.values["tsdf"].astype(np.float16),
        "weight": stored.values["weight"],
        "color": np.clip(np.rint(colour / colour_scale), 0, 255).astype(np.uint8),
        "color_scale": np.array(colour_scale, np.float64),
        "block_resolution": np.array(stored.block_resolution, np.int64),
        "voxel_size": np.array(stored.voxel_m, np.float64),
        "camera_positions": stored.camera_positions,
    }
    if stored.free_keys is not None and stored.free_values is not None:
        arrays |= {
            "free_voxel_size": np.array(stored.free_voxel_m, np.float64),
            "free_key": stored.free_keys,
            "free_tsdf": stored.free_values["tsdf"].astype(np.float16),
            "free_weight": stored.free_values["weight"],
        }

    def write(tmp: str) -> None:
        # Level 1: most of level 6's size (6.4 against 5.8 MB) in half the time (0.5 s).
        method = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED
        with zipfile.ZipFile(tmp, "w", method, compresslevel=1 if compress else None) as z:
            for name, array in arrays.items():
                with z.open(f"{name}.npy", "w", force_zip64=True) as f:
                    np.lib.format.write_array(f, array, allow_pickle=False)

    atomic_write(path, write, suffix=".npz", mode=0o644)


def read_tsdf(path: str | Path) -> StoredTSDF:
    """Read a file ``write_tsdf`` (or Open3D's ``VoxelBlockGrid.save``) wrote. Raises what numpy
    and zipfile raise on a damaged file, and ValueError on an unknown format."""
    with np.load(path, allow_pickle=False) as stored:
        voxel_m = float(np.ravel(stored["voxel_size"])[0])
        resolution = int(np.ravel(stored["block_resolution"])[0])
        cameras = stored["camera_positions"] if "camera_positions" in stored else None
        if "format" not in stored:
            return StoredTSDF(voxel_m, resolution, cameras)
        if str(stored["format"]) != FILE_FORMAT:
            raise ValueError(f"unknown map format {stored['format']}")
        values = {
            "tsdf": stored["tsdf"].astype(np.float32),
            "weight": stored["weight"].astype(np.float32),
            "color": stored["color"].astype(np.float32) * np.float32(stored["color_scale"]),
        }
        out = StoredTSDF(voxel_m, resolution, cameras, stored["key"], values)
        if "free_key" in stored:
            out.free_voxel_m = float(stored["free_voxel_size"])
            out.free_keys = stored["free_key"]
            out.free_values = {
                "tsdf": stored["free_tsdf"].astype(np.float32),
                "weight": stored["free_weight"].astype(np.float32),
            }
        return out
