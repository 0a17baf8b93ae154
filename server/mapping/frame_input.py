"""A frame made ready for the TSDF's fusion (``TSDFMap.integrate``): its images in the types
Open3D's ``VoxelBlockGrid`` takes, and the pixels the blocks it touches are found from.

Open3D fuses a frame in two steps. Finding the blocks the frame's surfaces reach
(``compute_unique_block_coordinates``) costs per pixel: 2.4 ms for 640x480 of Kinect depth, one
thread. Integrating those blocks costs per voxel: for each voxel the one depth pixel its centre
projects to is read, so every pixel of the image costs next to nothing there (0.75 ms more for
640x480 than for 320x240, on the same blocks). So the blocks are found from every n-th pixel of
a depth image wider than ``TSDFConfig.block_search_width_px``, each way (320x240 of 640x480:
0.7 ms), and every pixel is fused into them. A skipped pixel lies within n - 1 pixels of a
searched one (7 mm at 4 m for n = 2, under a 2 cm voxel), so the search reaches one voxel
further than the truncation band: the blocks the skipped pixels' bands reach are found too,
except at a depth edge no searched pixel shares (there a band block or two may be left out).
Fusing every second pixel instead moved the surface by ~2 mm and changed 5 % of the drone's
occupancy cells on tum_fr1_xyz (benchmarks/README.md, "Mapper CPU").
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import cast

import cv2
import numpy as np

from server.geometry import Intrinsics
from server.geometry.arrays import Float32Array, GreyImage, RealArray
from server.mapping.config import TSDFConfig

# Open3D takes depth and colour as uint16 and uint8 (or both as float32, which would copy the
# colour to floats on every frame): depth is then in steps of 1 / depth_units(range) metres.
_UINT16_MAX = 65535


@dataclass(frozen=True)
class FusionFrame:
    """depth_m: (H, W) float32 metres, 0 where none counts (no measurement, or beyond the map's
    range); K: its intrinsics; depth_uint16 / depth_units is depth_m rounded to steps of
    1 / depth_units metres (0.06 mm for a 4 m range); colour_uint8: (H, W, 3) RGB at the depth
    image's size. search_uint16 and search_K: every ``step``-th pixel of depth_uint16 each way
    and its intrinsics, the pixels the blocks are found from; search_band_voxels: how far
    around them, in voxels."""

    depth_m: Float32Array
    K: Intrinsics
    depth_units: float
    depth_uint16: np.ndarray
    colour_uint8: GreyImage
    step: int
    search_uint16: np.ndarray
    search_K: Intrinsics
    search_band_voxels: float


def search_step(width: int, search_width_px: int) -> int:
    """Every how many pixels the blocks of a depth image ``width`` pixels wide are found from
    (``search_width_px`` 0: every pixel)."""
    if search_width_px <= 0 or width <= search_width_px:
        return 1
    return math.ceil(width / search_width_px)


def every_nth_pixel(K: Intrinsics, step: int) -> Intrinsics:
    """Intrinsics of the image made of every step-th pixel of K's, each way, from the first:
    the pixel u of the new image is the pixel step * u of K's (not the centre of a step x step
    block, as ``Intrinsics.scaled`` assumes for a resized image)."""
    if step == 1:
        return K
    return Intrinsics(
        fx=K.fx / step,
        fy=K.fy / step,
        cx=K.cx / step,
        cy=K.cy / step,
        width=math.ceil(K.width / step),
        height=math.ceil(K.height / step),
    )


def depth_units(depth_max_m: float) -> float:
    """Steps per metre of a uint16 depth image that reaches ``depth_max_m``."""
    return float(math.floor(_UINT16_MAX / depth_max_m))


def intrinsics_at(K: Intrinsics, w: int, h: int) -> Intrinsics:
    """K rescaled to an image of w x h pixels (same aspect ratio, to a pixel); ValueError when
    the aspect differs."""
    if (K.width, K.height) == (w, h):
        return K
    factor = w / K.width
    if abs(K.height * factor - h) > 1.0:
        raise ValueError(f"depth {w}x{h} has not the aspect of intrinsics {K.width}x{K.height}")
    return K.scaled(factor)


def open3d_projection(K: Intrinsics) -> RealArray:
    """K's matrix for Open3D's integration, which reads the depth pixel a voxel projects into by
    truncating its image coordinates: pixel u spans [u, u + 1) there, where ours is centred on u.
    Half a pixel added to the principal point makes that the nearest pixel. Without it every
    voxel read depth half a pixel off: on the synthetic_room0 frames that tests/unit/mapping/
    test_tsdf.py fuses (exact poses), surface points lay 5.0 mm from the measured surface
    (median) instead of 4.9 at 640x480, and 6.6 instead of 4.9 for depth at 160x120 (measured
    once; the test holds the 160x120 map to the resampled one's). Only integration reads
    pixels so: the block search unprojects pixels (``search_K``), whose centres are ours."""
    return np.array([[K.fx, 0, K.cx + 0.5], [0, K.fy, K.cy + 0.5], [0, 0, 1.0]])


def at_depth_size(colour_rgb_uint8: GreyImage, depth_m: RealArray) -> GreyImage:
    """The colour resized to the depth image (area interpolation: each depth pixel gets the mean
    of the colour pixels it covers), as the map fuses it; unchanged when the sizes agree."""
    h, w = np.shape(depth_m)[:2]
    colour = np.asarray(colour_rgb_uint8)
    if colour.shape[:2] == (h, w):
        return colour
    # cv2.resize keeps the dtype; its stubs do not say so.
    return cast(GreyImage, cv2.resize(colour, (w, h), interpolation=cv2.INTER_AREA))


def fusion_frame(
    colour_rgb_uint8: GreyImage, depth_m: RealArray, K: Intrinsics, cfg: TSDFConfig
) -> FusionFrame:
    """A frame as the map fuses it (arguments as ``TSDFMap.integrate``, checked there): the
    colour resized to the depth image (area interpolation) when its size differs, K rescaled to
    it. ValueError when K's aspect is not the depth image's."""
    depth = np.asarray(depth_m, dtype=np.float32)
    h, w = depth.shape
    K = intrinsics_at(K, w, h)
    valid = np.isfinite(depth) & (depth > 0) & (depth <= cfg.depth_max_m)
    depth = np.where(valid, depth, np.float32(0))
    colour = at_depth_size(colour_rgb_uint8, depth)
    units = depth_units(cfg.depth_max_m)
    depth_uint16 = np.rint(depth * np.float32(units)).astype(np.uint16)
    step = search_step(w, cfg.block_search_width_px)
    search = np.ascontiguousarray(depth_uint16[::step, ::step]) if step > 1 else depth_uint16
    return FusionFrame(
        depth_m=depth,
        K=K,
        depth_units=units,
        depth_uint16=depth_uint16,
        colour_uint8=np.ascontiguousarray(colour),
        step=step,
        search_uint16=search,
        search_K=every_nth_pixel(K, step),
        search_band_voxels=cfg.trunc_voxels + (1.0 if step > 1 else 0.0),
    )
