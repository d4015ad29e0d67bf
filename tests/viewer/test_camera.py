"""A viser camera becomes our Camera with the right conventions (stg_runtime.viewer.camera)."""
import numpy as np
import pytest

from stg_runtime import Camera
from stg_runtime.viewer.camera import (camera_from_viser, matrix_to_quaternion, quaternion_to_matrix, scaled,
                                       viser_pose)


def test_quaternions_round_trip():
    rng = np.random.default_rng(0)
    for _ in range(50):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        q = -q if q[0] < 0 else q
        R = quaternion_to_matrix(q)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(matrix_to_quaternion(R), q, atol=1e-12)


def test_viser_camera_looks_along_z_with_y_down():
    """viser's wxyz is the camera-to-world rotation (OpenCV axes), position the centre: a camera at
    (1, 2, 3) turned 90 degrees about world y looks along world +x, and world -y is up in its image."""
    wxyz = [np.cos(np.pi / 4), 0.0, np.sin(np.pi / 4), 0.0]  # 90 degrees about y: camera z -> world x
    cam = camera_from_viser(wxyz, [1, 2, 3], fov=np.radians(60), width=64, height=48)
    np.testing.assert_allclose(cam.center, [1, 2, 3], atol=1e-12)
    (uv,), (depth,) = cam.project([[5, 2, 3]])
    np.testing.assert_allclose(uv, [32, 24], atol=1e-9)  # on the axis: the image centre (pixel centres +0.5)
    assert depth == pytest.approx(4.0)
    (above,), _ = cam.project([[5, 1, 3]])  # world -y is up: a smaller row
    assert above[1] < 24 and above[0] == pytest.approx(32)
    (top,), _ = cam.project([[5, 2 - 4 * np.tan(np.radians(30)), 3]])  # the top edge at half the fov
    assert top[1] == pytest.approx(0.0, abs=1e-9)
    assert cam.fx == cam.fy == pytest.approx(24 / np.tan(np.radians(30)))


def test_our_camera_to_viser_and_back():
    cam = Camera.look_at([0.5, -1, 2], [0, 0, 6], [0, -1, 0], fov_deg=47, width=320, height=200)
    pose = viser_pose(cam, distance=3.0)
    back = camera_from_viser(pose.wxyz, pose.position, pose.fov, cam.width, cam.height)
    np.testing.assert_allclose(back.world_to_camera, cam.world_to_camera, atol=1e-12)
    assert (back.fx, back.fy, back.cx, back.cy) == pytest.approx((cam.fx, cam.fy, cam.cx, cam.cy))
    np.testing.assert_allclose(np.linalg.norm(pose.look_at - cam.center), 3.0)
    np.testing.assert_allclose(cam.project([pose.look_at])[0][0], [160, 100], atol=1e-9)
    np.testing.assert_allclose(pose.up_direction, -cam.R[1], atol=1e-12)


def test_scaled_keeps_the_view():
    cam = Camera.look_at([0, 0, 0], [0, 0, 5], [0, -1, 0], fov_deg=50, width=1920, height=1080)
    small = scaled(cam, 320 * 180)
    assert (small.width, small.height) == (320, 180)
    assert small.fy / small.height == pytest.approx(cam.fy / cam.height)
    assert scaled(small, 10**9) is small
