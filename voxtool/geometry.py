"""Rigid transforms: quaternions, pose application, interpolation."""

from __future__ import annotations

import numpy as np


def quat_to_matrix(qw: float, qx: float, qy: float, qz: float) -> np.ndarray:
    """Rotation matrix of a unit quaternion (w, x, y, z), float64. The quaternion is normalized."""
    q = np.array([qw, qx, qy, qz], dtype=np.float64)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix_to_quat(r: np.ndarray) -> np.ndarray:
    """(w, x, y, z) of a rotation matrix (Shepperd's method)."""
    m = np.asarray(r, dtype=np.float64)
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0:
        s = np.sqrt(tr + 1.0) * 2
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif m[1, 1] > m[2, 2]:
        s = np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    q = np.array(q)
    return q / np.linalg.norm(q)


class Pose:
    """A rigid transform p' = R p + t (float64)."""

    __slots__ = ("rotation", "translation")

    def __init__(self, rotation: np.ndarray, translation: np.ndarray) -> None:
        self.rotation = np.asarray(rotation, dtype=np.float64)
        self.translation = np.asarray(translation, dtype=np.float64)

    @classmethod
    def from_quat(cls, t: tuple | np.ndarray, qw: float, qx: float, qy: float, qz: float) -> Pose:
        return cls(quat_to_matrix(qw, qx, qy, qz), np.asarray(t, dtype=np.float64))

    @classmethod
    def identity(cls) -> Pose:
        return cls(np.eye(3), np.zeros(3))

    def compose(self, other: Pose) -> Pose:
        """self * other: apply `other` first, then `self`."""
        return Pose(self.rotation @ other.rotation, self.rotation @ other.translation + self.translation)

    def is_identity(self) -> bool:
        return bool(np.array_equal(self.rotation, np.eye(3)) and not self.translation.any())

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Transform (N, 3) points in float64 and round to float32 (OctoMap's point3d)."""
        pts = np.asarray(points, dtype=np.float64)
        if self.is_identity():
            return pts.astype(np.float32)
        return (pts @ self.rotation.T + self.translation).astype(np.float32)


def planar_pose(x: float, y: float, yaw: float) -> np.ndarray:
    """The 4 x 4 pose of a position (x, y) and heading `yaw` in the plane (z, roll and pitch 0)."""
    out = np.eye(4)
    out[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    out[:2, 3] = x, y
    return out


def interpolate_pose(t: float, t0: float, p0: Pose, t1: float, p1: Pose) -> Pose:
    """Linear translation and slerp rotation between two stamped poses."""
    if t1 == t0:
        return p0
    a = (t - t0) / (t1 - t0)
    q0 = matrix_to_quat(p0.rotation)
    q1 = matrix_to_quat(p1.rotation)
    dot = float(np.dot(q0, q1))
    if dot < 0:
        q1, dot = -q1, -dot
    if dot > 0.9995:
        q = q0 + a * (q1 - q0)
    else:
        theta = np.arccos(dot)
        q = (np.sin((1 - a) * theta) * q0 + np.sin(a * theta) * q1) / np.sin(theta)
    q /= np.linalg.norm(q)
    return Pose(quat_to_matrix(*q), (1 - a) * p0.translation + a * p1.translation)
