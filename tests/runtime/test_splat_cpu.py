"""The CPU splatter (stg_runtime.splat_cpu) against the float64 oracle of formats/stg-v1.md, section 3
(stg_runtime.spec.rasterize_oracle), and both against hand-computed cases."""
from __future__ import annotations

import numpy as np
import pytest

from stg_runtime.camera import Camera
from stg_runtime.splat_cpu import rasterize
from stg_runtime.spec import MAX_ALPHA, T_STOP, project_oracle, rasterize_oracle

from tests.scenes import clean_scenes, random_scene

#: float32 against float64 on the same inputs: features and alpha are sums of at most a few hundred
#: terms of size <= 1, each with a relative error ~1e-7 (float32 rounding; exp ~2e-7), so 1e-4 is a
#: wide bound as long as no decision (alpha >= 1/255, the stop, the footprint) is within rounding of
#: its threshold. Depth is sum w z / alpha, so its error scales with z: the bound is 1e-4 * max(1, z)
#: where alpha > 0.5.
TOL = 1e-4


@pytest.mark.parametrize("size, channels, m, seed", [
    ((64, 48), 3, 200, 0),
    ((64, 48), 9, 120, 1),
    ((50, 37), 3, 80, 2),
    ((50, 37), 9, 200, 3),
    ((50, 37), 1, 40, 4),
    ((33, 70), 4, 150, 5),
])
def test_matches_oracle(size, channels, m, seed):
    for arrays, camera, (ref_f, ref_a, ref_d) in clean_scenes(seed, 3, m, *size, channels):
        f, a, d = rasterize(*arrays, camera)
        assert f.shape == (camera.height, camera.width, channels) and f.dtype == np.float32
        assert a.shape == d.shape == (camera.height, camera.width)
        assert np.abs(f - ref_f).max() < TOL
        assert np.abs(a - ref_a).max() < TOL
        solid = ref_a > 0.5
        assert solid.any() and (ref_a == 0).any()  # the scenes are neither empty nor full
        assert np.all(np.abs(d - ref_d)[solid] < TOL * np.maximum(1.0, ref_d[solid]))
        assert np.all(d[a == 0] == 0)


@pytest.mark.parametrize("fov, channels, seed", [(120, 3, 10), (180, 9, 11), (200, 3, 12)])
def test_fisheye_matches_oracle(fov, channels, seed):
    """Fisheye cameras up to 200 degrees across, Gaussians up to 100 degrees off the axis (some straddle
    the image plane, z = 0, where they are culled)."""
    for arrays, camera, (ref_f, ref_a, ref_d) in clean_scenes(seed, 3, 200, 64, 48, channels, fisheye=fov):
        f, a, d = rasterize(*arrays, camera)
        assert np.abs(f - ref_f).max() < TOL and np.abs(a - ref_a).max() < TOL
        solid = ref_a > 0.5
        assert solid.any() and (ref_a == 0).any()
        assert np.all(np.abs(d - ref_d)[solid] < TOL * np.maximum(1.0, ref_d[solid]))


def test_matches_oracle_deep():
    """Opaque, many-layered scenes: most pixels reach the transmittance stop, and the final
    transmittance (>= 1e-4 where the stop was taken) matches the reference's to 1% wherever it is
    below 1e-2."""
    deep = 0
    for arrays, camera, (ref_f, ref_a, ref_d) in clean_scenes(6, 3, 300, 40, 30, 3, opacity=(0.6, 1.0),
                                                              size=(1.0, 8.0)):
        f, a, d = rasterize(*arrays, camera)
        assert np.abs(f - ref_f).max() < TOL
        assert np.abs(a - ref_a).max() < TOL
        solid = ref_a > 0.5
        assert np.all(np.abs(d - ref_d)[solid] < TOL * np.maximum(1.0, ref_d[solid]))
        ref_t, t = 1 - ref_a, 1 - a.astype(np.float64)
        opaque = ref_t < 1e-2
        assert np.all(np.abs(t[opaque] / ref_t[opaque] - 1) < 1e-2)
        deep += int(np.sum(ref_t < 1e-3))
    assert deep > 300


def test_tile_size_does_not_change_the_image():
    rng = np.random.default_rng(10)
    scenes = [random_scene(rng, 200, 50, 37, 9),  # and a deep one, where pixels stop early
              random_scene(rng, 300, 50, 37, 3, opacity=(0.6, 1.0), size=(1.0, 8.0))]
    for arrays, camera in scenes:
        base = rasterize(*arrays, camera, tile_size=16)
        for tile_size in (8, 5, 32, 1, 64):
            other = rasterize(*arrays, camera, tile_size=tile_size)
            for x, y in zip(base, other):
                assert np.array_equal(x, y)
    with pytest.raises(ValueError):
        rasterize(*arrays, camera, tile_size=65)


# -- hand-computed cases ------------------------------------------------------------------------
FX = 50.0


def axis_camera(width=64, height=48):
    """Identity pose; the principal point is the centre of pixel (31, 23)."""
    return Camera(FX, FX, 31.5, 23.5, width, height, np.eye(4))


def gaussians(rows, channels=3):
    """rows of (x, y, z, isotropic scale, opacity, feature value) -> rasterize's arrays."""
    rows = np.asarray(rows, dtype=np.float64)
    m = len(rows)
    quats = np.tile([1.0, 0.0, 0.0, 0.0], (m, 1))
    scales = np.repeat(rows[:, 3:4], 3, axis=1)
    features = np.repeat(rows[:, 5:6], channels, axis=1)
    return rows[:, :3], quats, scales, rows[:, 4], features


@pytest.mark.parametrize("render", [rasterize, rasterize_oracle])
@pytest.mark.parametrize("opacity", [0.7, 0.995])
def test_single_isotropic_gaussian(render, opacity):
    z, s, f = 2.0, 0.04, 0.8
    F, A, D = render(*gaussians([(0, 0, z, s, opacity, f)]), axis_camera())
    alpha = min(MAX_ALPHA, opacity)
    assert A[23, 31] == pytest.approx(alpha, abs=1e-6)
    assert F[23, 31] == pytest.approx([alpha * f] * 3, abs=1e-6)
    assert D[23, 31] == pytest.approx(z, abs=1e-5)
    # One pixel to the right: on the axis the Jacobian is diag(fx/z, fy/z), so the 2D variance is
    # (fx s / z)^2 + 0.3 in both directions.
    var = (FX * s / z) ** 2 + 0.3
    assert A[23, 32] == pytest.approx(opacity * np.exp(-0.5 / var), abs=1e-6)
    assert A[22, 30] == pytest.approx(opacity * np.exp(-1.0 / var), abs=1e-6)


@pytest.mark.parametrize("render", [rasterize, rasterize_oracle])
def test_footprint_cuts_at_radius(render):
    """r = ceil(3 sqrt(lambda_max)), lambda_max = m + sqrt(max(0.1, m^2 - det)) = var + sqrt(0.1) for an
    isotropic 2D covariance; pixels beyond r get nothing even where alpha would be >= 1/255."""
    z, s, o = 2.0, 0.35945, 0.995
    var = (FX * s / z) ** 2 + 0.3
    r = int(np.ceil(3 * np.sqrt(var + np.sqrt(0.1))))
    assert r == 28 and o * np.exp(-0.5 * (r + 1) ** 2 / var) > 1.2 / 255
    _, A, _ = render(*gaussians([(0, 0, z, s, o, 1.0)]), axis_camera(64, 64))
    row = A[23]
    assert row[31 + r] == pytest.approx(o * np.exp(-0.5 * r * r / var), abs=1e-6)
    assert row[31 - r] == pytest.approx(o * np.exp(-0.5 * r * r / var), abs=1e-6)
    assert row[31 + r + 1] == 0 and row[31 - r - 1] == 0
    assert A[23 + r + 1, 31] == 0 and A[23 + r, 31] > 0


@pytest.mark.parametrize("render", [rasterize, rasterize_oracle])
def test_culled_gaussians_render_nothing(render):
    rows = [(0, 0, -2.0, 0.5, 0.9, 1.0),  # behind the camera
            (0, 0, 0.01, 0.5, 0.9, 1.0),  # on the near plane (z <= 0.01 is culled)
            (0, 0, 2.0, 0.5, 0.9 / 255, 1.0),  # opacity below 1/255
            (20, 0, 2.0, 0.05, 0.9, 1.0)]  # far outside the image
    F, A, D = render(*gaussians(rows), axis_camera())
    assert not F.any() and not A.any() and not D.any()
    F, A, D = render(*gaussians([(0, 0, 0.0101, 0.001, 0.9, 1.0)]), axis_camera())
    assert A[23, 31] == pytest.approx(0.9, abs=1e-6)  # just beyond the near plane


@pytest.mark.parametrize("render", [rasterize, rasterize_oracle])
def test_depth_order_not_input_order(render):
    near = (0, 0, 2.0, 0.05, 0.6, 1.0)
    far = (0, 0, 3.0, 0.075, 0.5, -2.0)  # same footprint as `near`
    a = render(*gaussians([near, far]), axis_camera())
    b = render(*gaussians([far, near]), axis_camera())
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)
    F, A, D = a
    w_near, w_far = 0.6, (1 - 0.6) * 0.5
    assert F[23, 31, 0] == pytest.approx(w_near * 1.0 + w_far * -2.0, abs=1e-6)
    assert A[23, 31] == pytest.approx(w_near + w_far, abs=1e-6)
    assert D[23, 31] == pytest.approx((w_near * 2.0 + w_far * 3.0) / (w_near + w_far), abs=1e-5)


@pytest.mark.parametrize("render", [rasterize, rasterize_oracle])
def test_equal_depth_lower_index_first(render):
    first, second = (0, 0, 2.0, 0.05, 0.6, 1.0), (0, 0, 2.0, 0.05, 0.5, -2.0)
    F, _, _ = render(*gaussians([first, second]), axis_camera())
    assert F[23, 31, 0] == pytest.approx(0.6 * 1.0 + 0.4 * 0.5 * -2.0, abs=1e-6)
    F, _, _ = render(*gaussians([second, first]), axis_camera())
    assert F[23, 31, 0] == pytest.approx(0.5 * -2.0 + 0.5 * 0.6 * 1.0, abs=1e-6)


@pytest.mark.parametrize("render", [rasterize, rasterize_oracle])
def test_transmittance_stop(render):
    # Opacity 0.95 at the centre: T = 0.05, 0.0025, 1.25e-4, then 6.25e-6 < 1e-4, so the fourth
    # Gaussian and all behind it are not added; the pixel keeps T = 1.25e-4 >= 1e-4.
    rows = [(0, 0, 2.0 + 0.5 * i, 0.05 * (1 + 0.25 * i), 0.95, float(i + 1)) for i in range(8)]
    F, A, D = render(*gaussians(rows[::-1]), axis_camera())
    w = [0.95, 0.05 * 0.95, 0.0025 * 0.95]
    assert 1 - A[23, 31] == pytest.approx(0.05 ** 3, rel=1e-3)
    assert 1 - A[23, 31] >= T_STOP
    assert F[23, 31, 0] == pytest.approx(w[0] * 1 + w[1] * 2 + w[2] * 3, abs=1e-5)
    assert D[23, 31] == pytest.approx((w[0] * 2.0 + w[1] * 2.5 + w[2] * 3.0) / sum(w), abs=1e-5)
    # Opacity 1 is clamped to alpha 0.99: T = 0.01, then 0.01 * (1 - 0.98) = 2e-4, then
    # 2e-4 * (1 - 0.99) < 1e-4 stops. (Two clamped Gaussians in a row would land exactly on the
    # threshold, T = 0.01 * 0.01 = 1e-4, where float32 and float64 disagree.)
    rows = [(0, 0, 2.0 + 0.5 * i, 0.05 * (1 + 0.25 * i), o, float(i + 1))
            for i, o in enumerate([1.0, 0.98, 1.0, 1.0, 0.5])]
    F, A, _ = render(*gaussians(rows), axis_camera())
    assert 1 - A[23, 31] == pytest.approx(2e-4, rel=1e-3)
    assert F[23, 31, 0] == pytest.approx(0.99 * 1 + 0.01 * 0.98 * 2, abs=1e-5)


def test_empty_and_dtypes():
    cam = axis_camera(20, 10)
    empty = np.zeros((0, 3)), np.zeros((0, 4)), np.zeros((0, 3)), np.zeros(0), np.zeros((0, 5))
    for render in (rasterize, rasterize_oracle):
        F, A, D = render(*empty, cam)
        assert F.shape == (10, 20, 5) and not F.any() and not A.any() and not D.any()
    args = gaussians([(0, 0, 2.0, 0.05, 0.6, 1.0)])  # float64 inputs are accepted
    F, A, D = rasterize(*args, axis_camera())
    assert F.dtype == A.dtype == D.dtype == np.float32 and F.flags.c_contiguous


# -- projection ---------------------------------------------------------------------------------
def test_projection_is_pinhole():
    rng = np.random.default_rng(7)
    (means, quats, scales, _, _), camera = random_scene(rng, 100, 64, 48, 3)
    p = project_oracle(means, quats, scales, camera)
    cam = means.astype(np.float64) @ camera.R.T + camera.t
    front = cam[:, 2] > 0.01
    np.testing.assert_array_equal(p.visible, front)  # the blur keeps every determinant positive
    np.testing.assert_allclose(p.depth, cam[:, 2])
    u = camera.fx * cam[:, 0] / cam[:, 2] + camera.cx
    v = camera.fy * cam[:, 1] / cam[:, 2] + camera.cy
    np.testing.assert_allclose(p.mean2d[front], np.stack([u, v], axis=1)[front], rtol=1e-12, atol=1e-9)
    a, b, c = p.cov2d[front].T
    np.testing.assert_allclose(p.conic[front], np.stack([c, -b, a], axis=1) / (a * c - b * b)[:, None],
                               rtol=1e-12)
    m = 0.5 * (a + c)
    lambda_max = m + np.sqrt(np.maximum(0.1, m * m - (a * c - b * b)))
    np.testing.assert_array_equal(p.radius[front], np.ceil(3 * np.sqrt(lambda_max)))


def test_projection_jacobian_clamp():
    """A Gaussian far to the side: its 2D covariance uses x/z clamped to 1.3 tan(half fov)."""
    camera = axis_camera()
    x, z, s = 3.0, 1.0, 0.1
    p = project_oracle([[x, 0, z]], [[1, 0, 0, 0]], [[s, s, s]], camera)
    lim = (camera.width - camera.cx) / FX + 0.3 * camera.width / (2 * FX)
    J = np.array([[FX / z, 0, -FX * lim / z], [0, FX / z, 0]])
    cov = J @ (s * s * np.eye(3)) @ J.T + 0.3 * np.eye(2)
    np.testing.assert_allclose(p.cov2d[0], [cov[0, 0], cov[0, 1], cov[1, 1]], rtol=1e-12)
    assert p.mean2d[0, 0] == pytest.approx(FX * x / z + camera.cx)  # the mean is not clamped


def test_tile_lists_do_not_depend_on_how_the_depth_order_is_cut():
    """bin_tiles cuts the depth order into one piece per thread; the lists must come out the same (each
    tile's ids front to back) whatever the number of pieces."""
    from stg_runtime.splat_cpu import _bin_tiles, sort_by_depth

    rng = np.random.default_rng(5)
    m, tiles_x, tiles_y = 20000, 9, 7
    x0, y0 = rng.integers(0, tiles_x, m), rng.integers(0, tiles_y, m)
    tiles = np.stack([x0, np.minimum(x0 + rng.integers(0, 3, m), tiles_x - 1),
                      y0, np.minimum(y0 + rng.integers(0, 3, m), tiles_y - 1)], 1).astype(np.int32)
    tiles[rng.random(m) < 0.1, 0] = tiles_x  # culled: an empty range
    depth = rng.uniform(1, 5, m)
    order = sort_by_depth(tiles, depth)
    start, ids, work = _bin_tiles(order, tiles, tiles_x, tiles_y, 1)
    kept = tiles[:, 0] <= tiles[:, 1]
    for t in range(tiles_x * tiles_y):  # the single-piece lists against a direct construction
        tx, ty = t % tiles_x, t // tiles_x
        inside = kept & (tiles[:, 0] <= tx) & (tx <= tiles[:, 1]) & (tiles[:, 2] <= ty) & (ty <= tiles[:, 3])
        expected = order[inside[order]]
        np.testing.assert_array_equal(ids[start[t]:start[t + 1]], expected)
    for pieces in (2, 3, 7):
        other = _bin_tiles(order, tiles, tiles_x, tiles_y, pieces)
        for a, b in zip((start, ids, work), other):
            np.testing.assert_array_equal(a, b)
