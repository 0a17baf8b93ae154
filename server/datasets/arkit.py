"""What the iPhone recorders (Stray Scanner, Record3D) share: ARKit's camera axes and confidence.

ARKit's camera frame is x right, y up, z backwards (the camera looks along -z); this project's is
x right, y down, z forward. The two differ by a half turn about x, so a pose converts by
T_world_camera = T_world_arkitcamera @ diag(1, -1, -1, 1). The world frame is left as ARKit's
(metres, y up against gravity, origin and heading where the recording started): a device pose
track is the phone's own estimate in its own world, not ground truth in any map's frame.

ARKit rates each LiDAR depth pixel low (0), medium (1) or high (2) confidence.
"""

from __future__ import annotations

import numpy as np

from server.registration.preprocess import resample_depth

# Rotation taking ARKit camera axes to this project's (and back: it is its own inverse).
ARKIT_TO_CAMERA = np.diag([1.0, -1.0, -1.0, 1.0])
# Drop only low-confidence pixels by default: those sit on depth edges and far or dark surfaces
# and are often wrong by decimetres. Medium pixels are close to right and keep the far half of a
# room in the map; the tracker's own 3x3 stability check already rejects the unsteady ones.
# Pass min_confidence=2 for the cleanest (and sparsest) depth.
DEFAULT_MIN_CONFIDENCE = 1


def camera_poses_from_arkit(T_world_arkit: np.ndarray) -> np.ndarray:
    """ARKit camera poses (N, 4, 4) T_world_camera (camera x right, y up, z back) -> the same
    poses with this project's camera axes (x right, y down, z forward); world frame unchanged."""
    return np.asarray(T_world_arkit, dtype=np.float64) @ ARKIT_TO_CAMERA


def lidar_depth(
    depth_m: np.ndarray,
    confidence: np.ndarray | None,
    min_confidence: int,
    width: int,
    height: int,
) -> np.ndarray:
    """LiDAR depth (h, w) metres -> (height, width) float32 metres registered to the colour image.

    Pixels that are not finite, not positive, or rated below ``min_confidence`` (0 low, 1 medium,
    2 high; confidence (h, w) uint8, None = no map, keep all) become 0 = no measurement. The
    result is resampled by nearest neighbour to the colour's size, as the server does with phone
    depth, so that every consumer of a dataset sees depth and colour pixel for pixel.
    """
    depth = np.asarray(depth_m, dtype=np.float32)
    keep = np.isfinite(depth) & (depth > 0)
    if confidence is not None:
        if confidence.shape != depth.shape:
            raise ValueError(
                f"confidence map is {confidence.shape}, depth {depth.shape}; they must match"
            )
        keep &= confidence >= min_confidence
    depth = np.where(keep, depth, np.float32(0.0)).astype(np.float32)
    return resample_depth(depth, width, height)
