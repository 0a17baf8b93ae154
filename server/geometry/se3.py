"""SE(3) helpers: 4x4 homogeneous transforms in metres, named ``T_to_from``.

A tangent vector is ``xi = (omega, t)``, rotation first, as in the paper's eq. 8.
"""

from __future__ import annotations

import numpy as np

from server.geometry.arrays import FloatArray, RealArray


def hat(w: FloatArray) -> FloatArray:
    """Skew-symmetric matrix [w]_x with hat(w) @ v == cross(w, v)."""
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def exp_se3(xi: RealArray) -> FloatArray:
    """Exponential map of a twist ``xi = (omega, t)`` (rad, m) to a 4x4 transform."""
    omega, t = np.asarray(xi[:3], dtype=np.float64), np.asarray(xi[3:], dtype=np.float64)
    theta = float(np.linalg.norm(omega))
    W = hat(omega)
    if theta < 1e-10:
        R = np.eye(3) + W
        V = np.eye(3) + 0.5 * W
    else:
        a = np.sin(theta) / theta
        b = (1.0 - np.cos(theta)) / theta**2
        c = (theta - np.sin(theta)) / theta**3
        R = np.eye(3) + a * W + b * W @ W
        V = np.eye(3) + b * W + c * W @ W
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = V @ t
    return T


def adjoint(T: FloatArray) -> FloatArray:
    """The 6x6 adjoint of a transform for twists ``(omega, t)``: T exp(xi) T^-1 = exp(Ad_T xi)."""
    R, t = T[:3, :3], T[:3, 3]
    A = np.zeros((6, 6))
    A[:3, :3] = R
    A[3:, :3] = hat(t) @ R
    A[3:, 3:] = R
    return A


def invert(T: FloatArray) -> FloatArray:
    """Inverse of a rigid transform, without a general matrix inverse."""
    Ti = np.eye(4)
    R = T[:3, :3]
    Ti[:3, :3] = R.T
    Ti[:3, 3] = -R.T @ T[:3, 3]
    return Ti


def orthonormalize(T: FloatArray) -> FloatArray:
    """Project the rotation block back onto SO(3); repeated composition drifts off it."""
    U, _, Vt = np.linalg.svd(T[:3, :3])
    R = U @ Vt
    if np.linalg.det(R) < 0:
        U[:, -1] *= -1
        R = U @ Vt
    out: FloatArray = T.copy()
    out[:3, :3] = R
    return out


def rotation_angle_deg(T: FloatArray) -> float:
    """Rotation angle of a transform in degrees."""
    c = (np.trace(T[:3, :3]) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def pose_distance(T_a: FloatArray, T_b: FloatArray) -> float:
    """How far apart two poses are: the translation between them in metres plus 0.1 m per 10
    degrees of rotation (a ranking, not a metric of its own)."""
    T = invert(T_a) @ T_b
    return float(np.linalg.norm(T[:3, 3]) + 0.01 * rotation_angle_deg(T))


def pose_from_quaternion(t: FloatArray, q_xyzw: FloatArray) -> FloatArray:
    """4x4 transform from a translation and a unit quaternion (x, y, z, w), TUM order."""
    x, y, z, w = np.asarray(q_xyzw, dtype=np.float64) / np.linalg.norm(q_xyzw)
    R = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def quaternion_from_pose(T: FloatArray) -> FloatArray:
    """Unit quaternion (x, y, z, w) with w >= 0 of a transform's rotation."""
    R = T[:3, :3]
    tr = np.trace(R)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = np.array(
            [(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, s / 4]
        )
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + R[i, i] - R[j, j] - R[k, k])
        q = np.empty(4)
        q[i] = s / 4
        q[j] = (R[j, i] + R[i, j]) / s
        q[k] = (R[k, i] + R[i, k]) / s
        q[3] = (R[k, j] - R[j, k]) / s
    q /= np.linalg.norm(q)
    return q if q[3] >= 0 else -q
