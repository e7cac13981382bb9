"""Rigid transforms as 4x4 matrices (SE(3)): from a rotation vector, from a tool pose, inverted, and a
camera's view matrix (look_at); the rotation matrix about an axis.

View matrices V map world to camera coordinates with OpenCV's axes (z forward, y down, x to the right of
the image).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from geometry.orientation import rotation_from_wxyz


def pose_matrix(rotvec=(0.0, 0.0, 0.0), translation=(0.0, 0.0, 0.0)) -> np.ndarray:
    """4x4 of a rotation vector (rad) and a translation."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(np.asarray(rotvec, dtype=float)).as_matrix()
    T[:3, 3] = translation
    return T


def matrix_of(pose) -> np.ndarray:
    """4x4 of a tool pose (drivers.interfaces.Pose or alike): its orientation (w, x, y, z) if it has one,
    else a turn by alpha about the vertical."""
    if pose.orientation is not None:
        R = rotation_from_wxyz(pose.orientation)
    else:
        R = Rotation.from_euler("z", pose.alpha)
    T = np.eye(4)
    T[:3, :3] = R.as_matrix()
    T[:3, 3] = (pose.x, pose.y, pose.z)
    return T


def inverse(T: np.ndarray) -> np.ndarray:
    R, t = T[:3, :3], T[:3, 3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ t
    return out


def rotation(axis, angle: float) -> np.ndarray:
    """3x3 rotation by `angle` (rad) about `axis` (Rodrigues; the axis need not be of unit length)."""
    axis = np.asarray(axis, dtype=float)
    axis = axis / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * (k @ k)


def view_matrix(R_camera: np.ndarray, centre) -> np.ndarray:
    """V (world -> camera) of a camera at `centre` whose axes in world coordinates are the rows of R_camera."""
    V = np.eye(4)
    V[:3, :3] = R_camera
    V[:3, 3] = -R_camera @ centre
    return V


def look_at(position, target, right=(0.0, 1.0, 0.0)) -> np.ndarray:
    """V (world -> camera) of a camera at `position` looking at `target`, its image x axis along `right` as far
    as the viewing direction allows (the VR cells put the insertion axis across the image)."""
    position, target = np.asarray(position, float), np.asarray(target, float)
    z = target - position
    z /= np.linalg.norm(z)
    x = np.asarray(right, float) - (np.asarray(right, float) @ z) * z
    if np.linalg.norm(x) < 1e-9:  # looking along `right`: any perpendicular will do
        x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    return view_matrix(np.vstack([x, np.cross(z, x), z]), position)
