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


# -- fisheye cameras (OpenCV's fisheye model, formats/stg-v1.md section 1) --------------------------

K4 = (0.05, -0.01, 0.002, -0.0005)


def fisheye(k=K4, **kw):
    w2c = Camera.look_at([0.3, -0.2, 0.1], [0, 0, 5], [0, -1, 0], 50, 64, 48).world_to_camera
    return Camera(20.0, 21.0, 31.5, 24.5, 64, 48, w2c, "fish", "fisheye", k, **kw)


def test_fisheye_projection_is_opencv_fisheye():
    import cv2
    cam = fisheye()
    rng = np.random.default_rng(1)
    pts = cam.unproject(rng.uniform(0, 64, 50), rng.uniform(0, 48, 50), rng.uniform(0.5, 9, 50))
    K = np.array([[cam.fx, 0, cam.cx - 0.5], [0, cam.fy, cam.cy - 0.5], [0, 0, 1.0]])  # OpenCV's pixel centres
    rvec, _ = cv2.Rodrigues(cam.R)
    uv_cv, _ = cv2.fisheye.projectPoints(pts[None], rvec, cam.t, K, np.array(K4))
    uv, z = cam.project(pts)
    np.testing.assert_allclose(uv, uv_cv[0] + 0.5, atol=1e-9)
    # points beyond 90 degrees off the axis still have an image position (theta = atan2(r, z))
    behind = cam.center + cam.R.T @ np.array([1.0, 0.0, -0.2])
    uv_b, z_b = cam.project(behind)
    assert z_b < 0 and np.hypot(*(uv_b - [cam.cx, cam.cy])) > cam.fx * np.pi / 2


def test_fisheye_rays_invert_the_projection_and_round_trip():
    cam = fisheye()
    rng = np.random.default_rng(2)
    u, v, d = rng.uniform(0, 64, 40), rng.uniform(0, 48, 40), rng.uniform(0.5, 9, 40)
    pts = cam.unproject(u, v, d)
    uv, z = cam.project(pts)
    np.testing.assert_allclose(uv, np.stack([u, v], 1), atol=1e-9)
    np.testing.assert_allclose(z, d, atol=1e-9)
    rays = cam.ray_directions()
    np.testing.assert_allclose(np.linalg.norm(rays, axis=-1), 1, atol=1e-12)
    uv, _ = cam.project(cam.center + 2.0 * rays[7, 13])
    np.testing.assert_allclose(uv, [13.5, 7.5], atol=1e-9)
    # the optical axis and a 180-degree equidistant fisheye's image circle
    wide = Camera(10, 10, 32, 24, 64, 48, np.eye(4), model="fisheye")
    np.testing.assert_allclose(wide.camera_rays(32, 24), [0, 0, 1], atol=1e-15)
    np.testing.assert_allclose(wide.camera_rays(32 + 10 * np.pi / 2, 24), [1, 0, 0], atol=1e-12)


def test_fisheye_max_angle_and_rays_beyond_it():
    from stg_runtime.camera import fisheye_distort, fisheye_max_angle
    assert fisheye(k=(0, 0, 0, 0)).max_angle == np.pi and fisheye().max_angle == pytest.approx(2.1407, abs=1e-4)
    assert Camera.look_at([0, 0, 0], [0, 0, 1], [0, -1, 0], 50, 8, 8).max_angle == np.pi / 2
    k = (-0.3, 0.0, 0.0, 0.0)  # theta_d = theta - 0.3 theta^3 peaks at theta = 1/sqrt(0.9)
    assert fisheye_max_angle(k) == pytest.approx(1 / np.sqrt(0.9))
    cam = Camera(10, 10, 32, 24, 64, 48, np.eye(4), model="fisheye", distortion=k)
    edge = 10 * fisheye_distort(cam.max_angle, k)  # the image circle's radius in pixels
    inside, outside = cam.camera_rays([32 + 0.9 * edge, 32 + 1.2 * edge], 24)
    assert np.arccos(inside[2]) < cam.max_angle
    np.testing.assert_allclose(np.arccos(outside[2]), cam.max_angle, atol=1e-9)


def test_fisheye_resize_dict_and_bad_values():
    cam = fisheye()
    small = cam.resized(32, 24)
    assert small.model == "fisheye" and small.distortion == K4 and small.fx == cam.fx / 2
    d = cam.to_dict()
    assert d["model"] == "fisheye" and "fx" not in d and d["intrinsics"]["k3"] == K4[2]
    assert Camera.from_dict(d) == cam and Camera.from_dict(d) != Camera.from_dict({**d, "model": "fisheye",
                                                                                  "intrinsics": {**d["intrinsics"], "k1": 0}})
    assert "model" not in Camera.look_at([0, 0, 0], [0, 0, 1], [0, -1, 0], 50, 8, 8).to_dict()  # pinholes as before
    assert Camera(1, 1, 0, 0, 8, 8, np.eye(4), model="fisheye").distortion == (0.0, 0.0, 0.0, 0.0)
    with pytest.raises(ValueError, match="unknown camera model 'omni'"):
        Camera(1, 1, 0, 0, 8, 8, np.eye(4), model="omni")
    with pytest.raises(ValueError, match="unknown camera model 'omni'"):
        Camera.from_dict({**d, "model": "omni"})
    with pytest.raises(ValueError, match="4 finite distortion"):
        Camera(1, 1, 0, 0, 8, 8, np.eye(4), model="fisheye", distortion=(0.1, 0.2))
    with pytest.raises(ValueError, match="4 finite distortion"):
        Camera(1, 1, 0, 0, 8, 8, np.eye(4), model="fisheye", distortion=(0.1, 0.2, np.nan, 0))
    with pytest.raises(ValueError, match="pinhole camera takes 0"):
        Camera(1, 1, 0, 0, 8, 8, np.eye(4), distortion=(0.1,))


def test_fisheye_look_at_and_orbit_keep_the_lens():
    cam = Camera.look_at([0, 0, 0], [0, 0, 1], [0, -1, 0], 180, 100, 50, model="fisheye")
    assert cam.fy == pytest.approx(25 / (np.pi / 2))  # equidistant: the top edge is 90 degrees off the axis
    rig = [Camera.look_at([x, 0, 0], [0, 0, 5], [0, -1, 0], 120, 64, 48, model="fisheye") for x in (-0.5, 0.5)]
    rig = [Camera(c.fx, c.fy, c.cx, c.cy, 64, 48, c.world_to_camera, model="fisheye", distortion=K4) for c in rig]
    path = orbit(rig, 4)
    assert all(c.model == "fisheye" and c.distortion == K4 and c.fy == pytest.approx(rig[0].fy) for c in path)


def test_vertical_fov_of_both_models():
    assert Camera.look_at([0, 0, 0], [0, 0, 1], [0, -1, 0], 70, 64, 48).vertical_fov == pytest.approx(np.radians(70))
    wide = Camera.look_at([0, 0, 0], [0, 0, 1], [0, -1, 0], 200, 64, 48, model="fisheye")
    assert wide.vertical_fov == pytest.approx(np.radians(200))
    from stg_runtime.viewer.camera import MAX_FOV, viser_pose
    assert viser_pose(wide).fov == MAX_FOV  # the viewer shows it through a pinhole, as wide as it goes
