"""Conversions between 4x4 poses and the UR pose vector [x, y, z, rx, ry, rz] (metres, axis-angle radians).

UR controllers take and report orientation as a rotation vector: axis times angle, angle in [0, pi]. The conversions
go through a unit quaternion (Shepperd's method), which stays accurate for every angle, including 0 and pi where the
textbook formulas divide by sin(angle).
"""

from __future__ import annotations

import numpy as np

from spadscan.protocol.errors import DeviceError

ORTHONORMAL_TOL = 1e-6
"""Largest |R^T R - I| entry accepted for a rotation block."""


def rotvec_to_matrix(rotvec: np.ndarray) -> np.ndarray:
    """Rotation vector (3,) in radians -> rotation matrix (3, 3) (Rodrigues, series near angle 0)."""
    r = np.asarray(rotvec, dtype=np.float64).reshape(3)
    theta = float(np.linalg.norm(r))
    if theta < 1e-4:
        # Taylor series of sin(t)/t and (1-cos t)/t^2: exact to double precision at this size.
        a = 1.0 - theta**2 / 6.0
        b = 0.5 - theta**2 / 24.0
    else:
        a = np.sin(theta) / theta
        b = (1.0 - np.cos(theta)) / theta**2
    k = np.array([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]])
    return np.eye(3) + a * k + b * (k @ k)


def matrix_to_quaternion(rot: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) -> unit quaternion (4,) as (w, x, y, z) with w >= 0."""
    m = np.asarray(rot, dtype=np.float64)
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    # Shepperd: divide by the largest of 4w^2, 4x^2, 4y^2, 4z^2 so the square root never nears zero.
    cand = np.array([tr, m[0, 0], m[1, 1], m[2, 2]])
    i = int(np.argmax(cand))
    if i == 0:
        s = 2.0 * np.sqrt(max(1.0 + tr, 0.0))
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif i == 1:
        s = 2.0 * np.sqrt(max(1.0 + m[0, 0] - m[1, 1] - m[2, 2], 0.0))
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif i == 2:
        s = 2.0 * np.sqrt(max(1.0 - m[0, 0] + m[1, 1] - m[2, 2], 0.0))
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = 2.0 * np.sqrt(max(1.0 - m[0, 0] - m[1, 1] + m[2, 2], 0.0))
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    quat = np.asarray(q)
    quat /= np.linalg.norm(quat)
    return -quat if quat[0] < 0 else quat


def matrix_to_rotvec(rot: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) -> rotation vector (3,), angle in [0, pi]."""
    w, *v = matrix_to_quaternion(rot)
    v = np.asarray(v)
    s = float(np.linalg.norm(v))
    if s < 1e-12:
        # angle = 2 atan2(s, w) ~ 2 s / w: the vector part scaled by 2 / w (w ~ 1 here).
        return 2.0 * v / w
    return v * (2.0 * np.arctan2(s, w) / s)


def vector_to_pose(vec: np.ndarray) -> np.ndarray:
    """UR pose vector (6,) [x, y, z, rx, ry, rz] -> 4x4 pose (float64)."""
    v = np.asarray(vec, dtype=np.float64).reshape(-1)
    if v.shape != (6,) or not np.all(np.isfinite(v)):
        raise DeviceError(f"UR pose vector must be 6 finite numbers, got shape {v.shape}")
    pose = np.eye(4)
    pose[:3, :3] = rotvec_to_matrix(v[3:])
    pose[:3, 3] = v[:3]
    return pose


def pose_to_vector(pose: np.ndarray) -> np.ndarray:
    """4x4 pose (rotation orthonormal, last row 0 0 0 1, metres) -> UR pose vector (6,)."""
    check_pose(pose)
    p = np.asarray(pose, dtype=np.float64)
    return np.concatenate([p[:3, 3], matrix_to_rotvec(p[:3, :3])])


def check_pose(pose: np.ndarray, what: str = "pose") -> None:
    """Raise DeviceError unless `pose` is a finite 4x4 rigid transform (det +1 rotation, last row 0 0 0 1)."""
    p = np.asarray(pose)
    if p.shape != (4, 4):
        raise DeviceError(f"{what} must be a 4x4 matrix, got shape {p.shape}")
    p = p.astype(np.float64)
    if not np.all(np.isfinite(p)):
        raise DeviceError(f"{what} has non-finite entries")
    if np.abs(p[3] - [0.0, 0.0, 0.0, 1.0]).max() > ORTHONORMAL_TOL:
        raise DeviceError(f"{what} last row must be [0, 0, 0, 1], got {p[3].tolist()}")
    r = p[:3, :3]
    err = float(np.abs(r.T @ r - np.eye(3)).max())
    if err > ORTHONORMAL_TOL or np.linalg.det(r) < 0:
        raise DeviceError(f"{what} rotation is not a proper rotation (|R^T R - I| = {err:.2e}, tolerance "
                          f"{ORTHONORMAL_TOL:.0e})")


def rotation_angle(rot_a: np.ndarray, rot_b: np.ndarray) -> float:
    """Angle (rad) of the relative rotation between two rotation matrices (3, 3), in [0, pi]."""
    return float(np.linalg.norm(matrix_to_rotvec(np.asarray(rot_a).T @ np.asarray(rot_b))))
