"""Pose conventions: right-handed, metres, optical frames (x right, y down, z forward).

``T_a_b`` is a 4x4 homogeneous matrix mapping points from frame b to frame a, so
``T_a_c = T_a_b @ T_b_c``.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from .errors import BadInput


def make_transform(R: np.ndarray, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=np.float64).ravel()
    return T


def invert(T: np.ndarray) -> np.ndarray:
    R, t = T[:3, :3], T[:3, 3]
    return make_transform(R.T, -R.T @ t)


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply T_a_b to points (..., 3) given in frame b."""
    return points @ T[:3, :3].T + T[:3, 3]


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """T_world_cam of an optical frame at ``eye`` whose z axis points at ``target``."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:
        raise BadInput('look_at: viewing direction is parallel to up')
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return make_transform(np.stack([x, y, z], axis=1), eye)


def to_xyz_quat(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Translation and quaternion (x, y, z, w), the geometry_msgs/Pose order."""
    return T[:3, 3].copy(), Rotation.from_matrix(T[:3, :3]).as_quat()


def from_xyz_quat(xyz, quat) -> np.ndarray:
    return make_transform(Rotation.from_quat(quat).as_matrix(), xyz)


def to_rotvec_t(T: np.ndarray) -> np.ndarray:
    """(6,) rotation vector and translation: the pose parameters of least-squares problems."""
    return np.concatenate([Rotation.from_matrix(T[:3, :3]).as_rotvec(), T[:3, 3]])


def from_rotvec_t(v: np.ndarray) -> np.ndarray:
    return make_transform(Rotation.from_rotvec(v[:3]).as_matrix(), v[3:6])


def rotation_angle_deg(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """Angle of the rotation between two rotation matrices, in degrees."""
    cos = (np.trace(R_a.T @ R_b) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def perturb(T: np.ndarray, rot_deg: np.ndarray, trans_m: np.ndarray) -> np.ndarray:
    """T composed with a small rotation (rotation vector in degrees) and translation."""
    dT = make_transform(Rotation.from_rotvec(np.radians(rot_deg)).as_matrix(), trans_m)
    return T @ dT


def matrix_to_list(T: np.ndarray) -> list[list[float]]:
    return [[float(v) for v in row] for row in np.asarray(T)]


def matrix_from_list(rows) -> np.ndarray:
    T = np.asarray(rows, dtype=np.float64)
    if T.shape != (4, 4):
        raise BadInput(f'expected a 4x4 matrix, got shape {T.shape}')
    return T


def convergence_point(poses: list[np.ndarray]) -> np.ndarray:
    """The point closest (least squares) to every camera's optical axis (z of each pose)."""
    A, b = np.zeros((3, 3)), np.zeros(3)
    for T in poses:
        T = np.asarray(T, float)
        axis = T[:3, 2] / np.linalg.norm(T[:3, 2])
        P = np.eye(3) - np.outer(axis, axis)
        A += P
        b += P @ T[:3, 3]
    if len(poses) < 2 or np.linalg.cond(A) > 1e6:
        raise BadInput('cameras aimed from one direction have no convergence point')
    return np.linalg.solve(A, b)


def rigid_transform(value, what: str) -> np.ndarray:
    """``value`` (nested lists) as a finite 4x4 rigid transform, or a ValueError naming ``what``."""
    try:
        T = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise BadInput(f'{what}: not a 4x4 matrix of numbers ({e})') from e
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise BadInput(f'{what}: expected a finite 4x4 matrix, got shape {T.shape}')
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0 or not np.allclose(T[3], (0, 0, 0, 1)):
        raise BadInput(f'{what}: not a rigid transform (rotation and translation)')
    return T
