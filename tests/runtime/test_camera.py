import numpy as np
import pytest

from stg_runtime import Camera
from stg_runtime.camera import orbit


def test_look_at_projects_target_to_principal_point():
    cam = Camera.look_at([1, -2, 0.5], [0, 0, 5], [0, -1, 0], 60, 64, 48)
    p = cam.R @ np.array([0, 0, 5]) + cam.t
    assert p[2] > 0
    u, v = cam.fx * p[0] / p[2] + cam.cx, cam.fy * p[1] / p[2] + cam.cy
    assert (u, v) == pytest.approx((32, 24))
    np.testing.assert_allclose(cam.center, [1, -2, 0.5], atol=1e-12)
    np.testing.assert_allclose(cam.R @ cam.R.T, np.eye(3), atol=1e-12)
    # the world up direction (-y here) appears up in the image (negative image y)
    up = cam.R @ np.array([0, -1.0, 0])
    assert up[1] < 0


def test_vertical_fov():
    cam = Camera.look_at([0, 0, 0], [0, 0, 1], [0, -1, 0], 90, 100, 50)
    assert cam.fy == pytest.approx(25.0)


def test_constructors_say_their_pixel_convention_and_dict_round_trip():
    K = np.array([[500, 0, 320], [0, 510, 240], [0, 0, 1.0]])
    Rt = np.hstack([np.eye(3), [[0.1], [0.2], [0.3]]])
    native = Camera.from_colmap(K, Rt, 640, 480, name="a")
    assert (native.fx, native.fy, native.cx, native.cy) == (500, 510, 320, 240)
    cam = Camera.from_opencv(K, Rt, 640, 480, name="a")  # OpenCV: pixel centres at integers
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (500, 510, 320.5, 240.5)
    np.testing.assert_array_equal(cam.world_to_camera, native.world_to_camera)
    # OpenCV's projection of a point, in its own convention, lands on the same pixel as ours
    import cv2
    point = np.array([[0.4, -0.3, 2.0]])
    uv_cv, _ = cv2.projectPoints(point, np.zeros(3), np.array([0.1, 0.2, 0.3]), K, np.zeros(5))
    uv, _ = cam.project(point)
    np.testing.assert_allclose(uv[0], uv_cv[0, 0] + 0.5, atol=1e-9)  # OpenCV's pixel u covers [u-0.5, u+0.5)
    again = Camera.from_dict(cam.to_dict())
    assert again == cam and again != cam.resized(320, 240)
    np.testing.assert_array_equal(again.K, cam.K)


def test_ray_directions_hit_pixel_centres():
    cam = Camera.look_at([0.3, 0.1, -1], [0, 0, 4], [0, -1, 0], 40, 20, 10)
    rays = cam.ray_directions()
    np.testing.assert_allclose(np.linalg.norm(rays, axis=-1), 1, atol=1e-12)
    x = cam.center + 3.0 * rays[7, 13]  # a point on the ray of pixel (u=13, v=7)
    p = cam.R @ x + cam.t
    assert (cam.fx * p[0] / p[2] + cam.cx, cam.fy * p[1] / p[2] + cam.cy) == pytest.approx((13.5, 7.5))


def test_bad_cameras_raise():
    with pytest.raises(ValueError, match="size"):
        Camera(1, 1, 0, 0, 0, 10, np.eye(4))
    with pytest.raises(ValueError, match="focal"):
        Camera(-1, 1, 0, 0, 10, 10, np.eye(4))


def test_orbit_looks_at_target():
    rig = [Camera.look_at([x, 0, 0], [0, 0, 5], [0, -1, 0], 50, 64, 48) for x in (-0.5, 0, 0.5)]
    path = orbit(rig, 8, target=[0, 0, 5])
    assert len(path) == 8
    for cam in path:
        p = cam.R @ np.array([0, 0, 5.0]) + cam.t
        assert p[0] == pytest.approx(0, abs=1e-9) and p[1] == pytest.approx(0, abs=1e-9) and p[2] > 0
    centres = np.array([c.center for c in path])
    assert np.ptp(centres[:, 0]) > 0.3  # it moves


def test_project_unproject_round_trip():
    cam = Camera.look_at([0.3, -0.2, 0.1], [0, 0, 5], [0, -1, 0], 50, 64, 48)
    rng = np.random.default_rng(0)
    u, v, d = rng.uniform(0, 64, 20), rng.uniform(0, 48, 20), rng.uniform(0.5, 9, 20)
    pts = cam.unproject(u, v, d)
    uv, z = cam.project(pts)
    np.testing.assert_allclose(uv, np.stack([u, v], 1), atol=1e-9)
    np.testing.assert_allclose(z, d, atol=1e-9)
    np.testing.assert_allclose(cam.project([0, 0, 5.0])[0], [32, 24], atol=1e-9)
