"""Which pixels of each camera a set of 3D points covers: the holes that the combined initialisation
(stg_train.data.points, --init combined) fills with view-volume samples.

A pixel is covered when a point the camera sees (stg_train.data.visibility: in front of a pinhole,
within a fisheye's field of view) projects into a pixel at most `radius` pixels
from it (a disc of pixels around every projection's pixel). Occlusion is ignored: a point behind a surface still covers the
pixels it projects to, so the holes are, if anything, underestimated.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from stg_runtime.camera import Camera

from .visibility import pixel_hits

#: Coverage radius as a fraction of the image width (3 px at 160 px wide, 27 px at 1352).
RADIUS_FRACTION = 0.02


def coverage_radius(width: int, fraction: float = RADIUS_FRACTION) -> int:
    """The coverage radius in pixels for images `width` pixels wide (at least 1)."""
    return max(1, int(round(fraction * width)))


def covered_pixels(camera: Camera, xyz: np.ndarray, radius: int) -> np.ndarray:
    """(H, W) bool: pixels of `camera` within `radius` pixels of the projection of a point of xyz (N, 3)."""
    import cv2

    hit = np.zeros((camera.height, camera.width), np.uint8)
    if len(xyz):
        u, v, ok = pixel_hits(camera, xyz)
        hit[v[ok], u[ok]] = 1
    if radius > 0:
        dy, dx = np.mgrid[-radius:radius + 1, -radius:radius + 1]
        kernel = (dx * dx + dy * dy <= radius * radius).astype(np.uint8)
        hit = cv2.dilate(hit, kernel)
    return hit.astype(bool)


def coverage_masks(cameras: Sequence[Camera], xyz: np.ndarray, radius: int | None = None) -> np.ndarray:
    """(C, H, W) bool covered_pixels of each camera (all of one size); radius default coverage_radius."""
    if not cameras:
        raise ValueError("coverage_masks: no cameras")
    radius = coverage_radius(cameras[0].width) if radius is None else int(radius)
    return np.stack([covered_pixels(cam, xyz, radius) for cam in cameras])
