"""Which points a camera sees, and through which pixels: the test that the initialisation's samplers
(stg_train.data.volume), the coverage masks (coverage) and the depth bounds (bounds) share, for pinhole
and fisheye cameras (formats/stg-v1.md, section 1).

A pinhole sees the points in front of it (camera-space z > 0); a fisheye sees the points up to its
max_angle off the optical axis (stg_runtime.camera.Camera.max_angle: beyond 90 degrees, behind the
camera plane, for lenses wider than 180 degrees); both only where the points project inside the image.
"""
from __future__ import annotations

import numpy as np

from stg_runtime.camera import Camera

#: Pixels whose rays lie more than this many degrees off the optical axis get no view-volume samples:
#: a point at a positive depth z on such a ray lies more than z / cos(angle) away, beside the rig.
MAX_SAMPLE_ANGLE_DEG = 80.0


def sees(camera: Camera, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(uv (..., 2) continuous pixel coordinates, z (...,) camera-space depth, visible (...,) bool) of
    world points xyz (..., 3): visible when the camera sees the point (module docstring) inside its image."""
    xyz = np.asarray(xyz, np.float64)
    uv, z = camera.project(xyz)
    if camera.model == "fisheye":
        p = xyz @ camera.R.T + camera.t
        with np.errstate(invalid="ignore"):
            front = np.arctan2(np.hypot(p[..., 0], p[..., 1]), p[..., 2]) < camera.max_angle
    else:
        front = z > 0
    with np.errstate(invalid="ignore"):
        inside = (uv[..., 0] >= 0) & (uv[..., 0] < camera.width) & (uv[..., 1] >= 0) & (uv[..., 1] < camera.height)
    return uv, z, front & inside & np.isfinite(z)


def pixel_hits(camera: Camera, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixel columns u, rows v (int64, clipped into the image) that world points xyz (..., 3) project
    into, and the bool mask of the points the camera sees there (`sees`)."""
    uv, _, ok = sees(camera, xyz)
    uv = np.where(np.isfinite(uv), uv, 0.0)
    u = np.clip(np.floor(uv[..., 0]), 0, camera.width - 1).astype(np.int64)
    v = np.clip(np.floor(uv[..., 1]), 0, camera.height - 1).astype(np.int64)
    return u, v, ok


def samplable_pixels(camera: Camera, max_angle_deg: float = MAX_SAMPLE_ANGLE_DEG) -> np.ndarray:
    """(H, W) bool: the pixels whose rays (through their centres) lie at most max_angle_deg off the
    optical axis, which Camera.unproject can place at a positive depth; every pixel of a pinhole."""
    if camera.model != "fisheye":
        return np.ones((camera.height, camera.width), bool)
    u = np.arange(camera.width) + 0.5
    v = np.arange(camera.height) + 0.5
    rays = camera.camera_rays(u[None, :], v[:, None])
    return rays[..., 2] > np.cos(np.radians(max_angle_deg))
