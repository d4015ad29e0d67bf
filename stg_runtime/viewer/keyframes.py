"""Camera paths from keyframes: the viewer's "save camera path", as `stg-render --path` reads it (a list
of camera objects, one per output frame; stg_runtime.camera.save_camera_path)."""
from __future__ import annotations

from typing import Sequence

import numpy as np

from ..camera import Camera
from .camera import matrix_to_quaternion, quaternion_to_matrix


def slerp(q0: np.ndarray, q1: np.ndarray, s: float) -> np.ndarray:
    """Spherical interpolation of unit quaternions (wxyz) at s in [0, 1], along the shorter arc."""
    q0, q1 = np.asarray(q0, float), np.asarray(q1, float)
    dot = float(q0 @ q1)
    if dot < 0:
        q1, dot = -q1, -dot
    if dot > 0.9995:
        q = q0 + s * (q1 - q0)
    else:
        angle = np.arccos(dot)
        q = (np.sin((1 - s) * angle) * q0 + np.sin(s * angle) * q1) / np.sin(angle)
    return q / np.linalg.norm(q)


def interpolate_path(keyframes: Sequence[Camera], frames_between: int, width: int | None = None,
                     height: int | None = None) -> list[Camera]:
    """One camera per output frame through `keyframes`: each keyframe, then `frames_between` cameras
    between it and the next (rotation by slerp, centre and vertical field of view linearly), ending on
    the last keyframe. Every camera has the image size width x height (default: the first keyframe's)
    with the principal point at the image centre and square pixels."""
    keyframes = list(keyframes)
    if not keyframes:
        raise ValueError("a camera path needs at least one keyframe")
    if frames_between < 0:
        raise ValueError(f"frames_between must be >= 0, got {frames_between}")
    width = width or keyframes[0].width
    height = height or keyframes[0].height
    quats = [matrix_to_quaternion(k.R.T) for k in keyframes]
    fovs = [2 * np.arctan(0.5 * k.height / k.fy) for k in keyframes]
    path = []

    def camera_at(i: int, s: float) -> Camera:
        j = min(i + 1, len(keyframes) - 1)
        R_wc = quaternion_to_matrix(slerp(quats[i], quats[j], s))
        centre = (1 - s) * keyframes[i].center + s * keyframes[j].center
        f = 0.5 * height / np.tan(0.5 * ((1 - s) * fovs[i] + s * fovs[j]))
        w2c = np.eye(4)
        w2c[:3, :3] = R_wc.T
        w2c[:3, 3] = -R_wc.T @ centre
        return Camera(f, f, width / 2, height / 2, width, height, w2c, f"path{len(path):04d}")

    for i in range(len(keyframes) - 1):
        for k in range(frames_between + 1):
            path.append(camera_at(i, k / (frames_between + 1)))
    path.append(camera_at(len(keyframes) - 1, 0.0))
    return path
