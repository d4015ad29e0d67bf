"""Axis-angle vectors and rotation matrices (numpy, float64): Rodrigues' formula and its inverse.

A rotation vector v (3,) turns by |v| radians about v / |v|, right-handed."""
from __future__ import annotations

import numpy as np


def cross_matrix(v) -> np.ndarray:
    """(3, 3) matrix [v]x of the cross product with v (3,): [v]x u = v x u."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def rotation_from_axis_angle(v) -> np.ndarray:
    """(3, 3) rotation matrix of the axis-angle vector v (3,) (Rodrigues' formula; angle = |v| radians)."""
    v = np.asarray(v, dtype=np.float64)
    angle = float(np.linalg.norm(v))
    if angle < 1e-15:
        return np.eye(3)
    kx = cross_matrix(v / angle)
    return np.eye(3) + np.sin(angle) * kx + (1 - np.cos(angle)) * kx @ kx


def rotation_vector(rotation: np.ndarray) -> np.ndarray:
    """(3,) axis-angle (radians) of a (3, 3) rotation matrix, for angles below pi; exact to rounding
    for small angles too (cv2.Rodrigues returns 0 below about 1e-5 radians)."""
    vee = 0.5 * np.array([rotation[2, 1] - rotation[1, 2], rotation[0, 2] - rotation[2, 0],
                          rotation[1, 0] - rotation[0, 1]])
    angle = float(np.arccos(np.clip((np.trace(rotation) - 1.0) / 2.0, -1.0, 1.0)))
    return vee if angle < 1e-8 else vee * (angle / np.sin(angle))
