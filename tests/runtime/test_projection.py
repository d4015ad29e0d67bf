"""stg_runtime.projection.footprint, run as plain Python (numba compiles the same function for the CPU
and GPU splatters), against the float64 oracle's projection and a brute-force pixel test."""
from __future__ import annotations

import numpy as np
import pytest

from stg_runtime.camera import Camera
from stg_runtime.projection import CAMERA_PARAMS, camera_params, footprint, pixel_ray
from stg_runtime.spec import MAX_ALPHA, MIN_ALPHA, project_oracle

from tests.scenes import random_scene


def test_camera_params_layout():
    camera = Camera.look_at((1, 2, 3), (0, 0, 10), (0, -1, 0), 50, 64, 48)
    cam = camera_params(camera)
    assert len(cam) == CAMERA_PARAMS and all(type(v) is float for v in cam)
    np.testing.assert_array_equal(np.reshape(cam[:9], (3, 3)), camera.R)
    np.testing.assert_array_equal(cam[9:12], camera.t)
    assert cam[12:16] == (camera.fx, camera.fy, camera.cx, camera.cy)
    np.testing.assert_allclose(cam[16:19], camera.center)
    tan_x = camera.width / (2 * camera.fx)  # x/z is clamped to 1.3 x tan(half field of view) (centred)
    np.testing.assert_allclose(cam[19:21], [-1.3 * tan_x, 1.3 * tan_x])
    assert cam[23:] == (0.0, 0.0, 0.0, 0.0, 0.0, np.pi / 2)
    k = (0.05, -0.01, 0.002, -5e-4)
    fish = camera_params(Camera(30, 31, 12.5, 7.5, 24, 16, np.eye(4), model="fisheye", distortion=k))
    assert fish[23:28] == (1.0, *k) and fish[28] == pytest.approx(2.1407, abs=1e-4)


@pytest.mark.parametrize("fisheye", [None, 120, 190])
def test_footprint_matches_the_reference_and_covers_every_pixel_it_can_reach(fisheye):
    rng = np.random.default_rng(5)
    W, H = 64, 48
    (means, quats, scales, opacities, _), camera = random_scene(rng, 300, W, H, 3, opacity=(0.0, 0.3),
                                                                fisheye=fisheye)
    ref = project_oracle(means, quats, scales, camera)
    cam = camera_params(camera)
    px, py = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    drawn = empty = 0
    for i in range(len(opacities)):
        z, u, v, ca, cb, cc, thr, u0, u1, v0, v1 = footprint(cam, W, H, means, quats, scales, opacities, i)
        np.testing.assert_allclose(z, ref.depth[i], rtol=1e-12, atol=1e-12)
        if not (ref.visible[i] and opacities[i] >= MIN_ALPHA):
            assert u0 > u1, i
            continue
        # Every pixel centre within the radius where alpha reaches 1/255 must be in the rectangle.
        A, B, C = ref.conic[i]
        dx, dy = px - ref.mean2d[i, 0], py - ref.mean2d[i, 1]
        power = 0.5 * (A * dx * dx + C * dy * dy) + B * dx * dy
        alpha = np.minimum(MAX_ALPHA, opacities[i] * np.exp(-power))
        r = ref.radius[i]
        reach = (np.abs(dx) <= r) & (np.abs(dy) <= r) & (power >= 0) & (alpha >= MIN_ALPHA)
        ys, xs = np.nonzero(reach)
        if u0 > u1:
            assert not reach.any(), i
            empty += 1
            continue
        drawn += 1
        np.testing.assert_allclose([u, v], ref.mean2d[i], rtol=1e-12)
        np.testing.assert_allclose([2 * ca, cb, 2 * cc], ref.conic[i], rtol=1e-9)
        np.testing.assert_allclose(thr, np.log(255 * np.float64(opacities[i])) + 0.01, atol=1e-6)
        assert 0 <= u0 <= u1 < W and 0 <= v0 <= v1 < H and all(isinstance(k, int) for k in (u0, u1, v0, v1))
        assert np.all((xs >= u0) & (xs <= u1) & (ys >= v0) & (ys <= v1)), i
        # ... and no wider than the radius allows.
        assert u0 >= np.ceil(ref.mean2d[i, 0] - r - 0.5) and u1 <= np.floor(ref.mean2d[i, 0] + r - 0.5)
    assert drawn > 100 and empty > 5  # both cases were seen


def test_fisheye_culls_at_max_angle_and_behind_the_image_plane():
    """A fisheye draws Gaussians up to (not at) its max_angle off the axis, those with z > NEAR only."""
    k = (-0.3, 0.0, 0.0, 0.0)  # max_angle = 1/sqrt(0.9), about 63.6 degrees
    camera = Camera(10, 10, 32, 24, 64, 48, np.eye(4), model="fisheye", distortion=k)
    cam = camera_params(camera)
    ones = np.ones((1, 1), np.float32)
    for theta, drawn in [(camera.max_angle - 1e-3, True), (camera.max_angle + 1e-3, False)]:
        mean = np.array([[np.sin(theta), 0.0, np.cos(theta)]], np.float32) * 2
        fp = footprint(cam, 64, 48, mean, np.array([[1, 0, 0, 0]], np.float32), 0.05 * ones.repeat(3, 1),
                       ones[0], 0)
        assert (fp[7] <= fp[8]) == drawn, theta
        assert ref_visible(mean, camera) == drawn
    wide = Camera(10, 10, 32, 24, 64, 48, np.eye(4), model="fisheye")  # 180 degrees across 31 pixels
    for z, drawn in [(0.011, True), (0.009, False), (-0.5, False)]:
        mean = np.array([[1.0, 0.0, z]], np.float32)
        fp = footprint(camera_params(wide), 64, 48, mean, np.array([[1, 0, 0, 0]], np.float32),
                       np.full((1, 3), 0.05, np.float32), ones[0], 0)
        assert (fp[7] <= fp[8]) == drawn and np.all(np.isfinite(fp[:7])), z


def ref_visible(mean, camera):
    return bool(project_oracle(mean, [[1, 0, 0, 0]], [[0.05] * 3], camera).visible[0])


def test_pixel_ray_is_the_cameras_ray():
    import numba
    ray = numba.njit(pixel_ray)
    cameras = [Camera.look_at([1, 2, 3], [0, 0, 0], [0, -1, 0], 60, 24, 16),
               Camera.look_at([1, 2, 3], [0, 0, 0], [0, -1, 0], 200, 24, 16, model="fisheye"),
               Camera(30, 31, 12.5, 7.5, 24, 16, np.eye(4), model="fisheye", distortion=(0.05, -0.01, 0.002, -5e-4)),
               Camera(5, 5, 12, 8, 24, 16, np.eye(4), model="fisheye", distortion=(-0.3, 0, 0, 0))]  # beyond its circle
    for camera in cameras:
        cam = camera_params(camera)
        got = np.array([[ray(cam, u + 0.5, v + 0.5) for u in range(24)] for v in range(16)])
        np.testing.assert_allclose(got, camera.ray_directions(), atol=1e-12)
