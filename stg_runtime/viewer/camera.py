"""A viser camera <-> our `Camera` (formats/stg-v1.md, section 1).

viser reports a browser's camera as `wxyz` (the camera-to-world rotation R_wc as a unit quaternion,
w first), `position` (the camera centre in world coordinates), `fov` (the vertical field of view in
radians) and the canvas size in pixels, with OpenCV axes (x right, y down, z forward), as we use.
Our Camera is world-to-camera: R = R_wc^T, t = -R_wc^T position. Square pixels; the principal point is
the image centre, which with pixel centres at +0.5 is (width / 2, height / 2).
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ..camera import Camera


class ViserPose(NamedTuple):
    """What viser needs to show our camera: wxyz (4,) camera-to-world rotation, position (3,) camera
    centre, fov vertical in radians, look_at (3,) a point `distance` ahead on the optical axis, and
    up_direction (3,) the world direction that is up in the image (-y of the camera)."""

    wxyz: np.ndarray
    position: np.ndarray
    fov: float
    look_at: np.ndarray
    up_direction: np.ndarray


def quaternion_to_matrix(wxyz) -> np.ndarray:
    """(4,) quaternion w, x, y, z (normalised here) -> (3, 3) rotation matrix."""
    w, x, y, z = np.asarray(wxyz, dtype=np.float64) / np.linalg.norm(wxyz)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def matrix_to_quaternion(R) -> np.ndarray:
    """(3, 3) rotation matrix -> (4,) unit quaternion w, x, y, z with w >= 0."""
    R = np.asarray(R, dtype=np.float64)
    # the largest of 4w^2, 4x^2, 4y^2, 4z^2 gives the best-conditioned formula
    diag = np.array([np.trace(R), R[0, 0] - R[1, 1] - R[2, 2], R[1, 1] - R[0, 0] - R[2, 2],
                     R[2, 2] - R[0, 0] - R[1, 1]])
    k = int(np.argmax(diag))
    s = 2.0 * np.sqrt(max(1.0 + diag[k], 1e-300))
    if k == 0:
        q = [s / 4, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif k == 1:
        q = [(R[2, 1] - R[1, 2]) / s, s / 4, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif k == 2:
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, s / 4, (R[1, 2] + R[2, 1]) / s]
    else:
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, s / 4]
    q = np.array(q) / np.linalg.norm(q)
    return -q if q[0] < 0 else q


#: The widest vertical field of view (radians) the viewer's pinhole shows a (fisheye) camera with.
MAX_FOV = float(np.radians(120.0))


def camera_from_viser(wxyz, position, fov: float, width: int, height: int, name: str = "viewer") -> Camera:
    """Our Camera for a viser camera state (see the module docstring); width x height in pixels."""
    R_wc = quaternion_to_matrix(wxyz)
    w2c = np.eye(4)
    w2c[:3, :3] = R_wc.T
    w2c[:3, 3] = -R_wc.T @ np.asarray(position, dtype=np.float64)
    f = 0.5 * height / np.tan(0.5 * fov)
    return Camera(f, f, width / 2, height / 2, width, height, w2c, name)


def viser_pose(camera: Camera, distance: float = 1.0) -> ViserPose:
    """The viser pose of `camera` (the inverse of camera_from_viser for its pose and vertical field of
    view; a camera with fx != fy or an off-centre principal point is shown with its vertical fov, a
    fisheye as a pinhole of its vertical fov up to MAX_FOV)."""
    R_wc = camera.R.T
    centre = camera.center
    fov = min(camera.vertical_fov, MAX_FOV)
    return ViserPose(matrix_to_quaternion(R_wc), centre, fov, centre + distance * R_wc[:, 2], -R_wc[:, 1])


def scaled(camera: Camera, max_pixels: int) -> Camera:
    """`camera` resized (same field of view) to at most `max_pixels` pixels, or as it is when smaller."""
    pixels = camera.width * camera.height
    if pixels <= max_pixels:
        return camera
    s = np.sqrt(max_pixels / pixels)
    return camera.resized(max(1, int(camera.width * s)), max(1, int(camera.height * s)))
