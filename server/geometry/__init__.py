from server.geometry.camera import Intrinsics, backproject, backproject_pixels, project
from server.geometry.se3 import (
    adjoint,
    exp_se3,
    hat,
    invert,
    orthonormalize,
    pose_distance,
    pose_from_quaternion,
    quaternion_from_pose,
    rotation_angle_deg,
)

__all__ = [
    "Intrinsics",
    "backproject",
    "backproject_pixels",
    "project",
    "adjoint",
    "exp_se3",
    "hat",
    "invert",
    "orthonormalize",
    "pose_distance",
    "pose_from_quaternion",
    "quaternion_from_pose",
    "rotation_angle_deg",
]
