"""Keyframes: the reference images the current frame is tracked against."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from server.geometry import Intrinsics, backproject_pixels
from server.geometry.arrays import Float32Array, FloatArray, GreyImage
from server.registration.config import RegistrationConfig
from server.registration.dense import DenseModel, build_dense_model
from server.registration.features import detect_features
from server.registration.preprocess import sample_stable_depth
from server.registration.sparse import point_information


@dataclass
class Keyframe:
    """A frame whose corners are tracked by the following frames.

    points: (M, 3) corners back-projected in this keyframe's camera frame, metres.
    covariances: (M, 3, 3) their noise, m^2.
    """

    id: int
    frame_index: int
    T_world_keyframe: FloatArray
    grey: GreyImage
    uv: Float32Array  # (M, 2) corner pixels
    points: FloatArray
    covariances: FloatArray
    dense: DenseModel | None
    # The map segment it belongs to (Tracker: 0 is the map; a new segment starts after a loss
    # that nothing recovered, and merges into 0 when place recognition links them). Poses of
    # two segments are in two worlds until then.
    segment: int = 0
    depth: Float32Array | None = None  # cleaned, metres: kept to build ``dense`` when needed

    def surface(self, K: Intrinsics) -> DenseModel | None:
        """The keyframe's surface (``dense``, or built from its kept depth, seen with ``K``,
        once); None when it keeps neither."""
        if self.dense is None and self.depth is not None:
            self.dense = build_dense_model(self.depth, K)
            self.depth = None
        return self.dense


def make_keyframe(
    kf_id: int,
    frame_index: int,
    T_world_camera: FloatArray,
    grey: GreyImage,
    depth: Float32Array,
    K: Intrinsics,
    cfg: RegistrationConfig,
) -> Keyframe:
    """Detect corners with trusted depth in a frame and make it a keyframe."""
    uv = detect_features(grey, cfg.features, mask=depth > 0)
    z = sample_stable_depth(depth, uv, cfg.depth)
    uv = uv[z > 0]
    points = backproject_pixels(uv.astype(np.float64), z[z > 0], K)
    dense = build_dense_model(depth, K, grey) if cfg.solver.dense else None
    # Without dense refinement only a relocalisation that flow cannot follow needs the surface
    # (relocalise.align_to_surface): its depth is kept and the surface built then (surface()),
    # not for every keyframe (~15 ms each on 640x480).
    keep_depth = dense is None and cfg.relocalise.enabled
    return Keyframe(
        id=kf_id,
        frame_index=frame_index,
        T_world_keyframe=T_world_camera.copy(),
        grey=grey,
        uv=uv,
        points=points,
        covariances=point_information(points, K, cfg.depth),
        dense=dense,
        depth=depth if keep_depth else None,
    )
