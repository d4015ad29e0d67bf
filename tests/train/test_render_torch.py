"""The torch splatter (stg_train.render.torch_splat) against the float64 oracle and the numba splatter,
and its gradients."""
import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from stg_runtime.camera import Camera  # noqa: E402
from stg_runtime.spec import rasterize_oracle  # noqa: E402
from stg_train.params import gaussians_at as evaluate  # noqa: E402
from stg_train.render import RenderOutput, rasterize  # noqa: E402


@pytest.fixture(autouse=True)
def _one_thread():
    """Small tensors: threads only add contention on shared CI cores. Per test, because numba's OpenMP
    layer resets the process's OpenMP thread count (which torch shares) when it runs."""
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


def _camera(width, height):
    """Off-centre principal point, fx != fy, looking slightly sideways."""
    cam = Camera.look_at([0.1, -0.2, 0.0], [0.3, 0.1, 4.0], [0, -1, 0], 60.0, width, height)
    return Camera(cam.fx, cam.fy * 1.1, cam.cx + 0.07 * width, cam.cy - 0.06 * height, width, height,
                  cam.world_to_camera, "test")


def _scene(seed, width, height, channels, n=80, dense=False):
    """Random Gaussians, some behind the camera, at the near plane, partly or wholly off-screen."""
    rng = np.random.default_rng(seed)
    cam = _camera(width, height)
    z = rng.uniform(1.0, 5.0, n) if dense else rng.uniform(-0.5, 7.0, n)
    xy = rng.uniform(-0.8, 0.8, (n, 2)) * np.maximum(z, 1.0)[:, None] * (0.4 if dense else 1.0)
    cam_pts = np.concatenate([xy, z[:, None]], 1)
    cam_pts[:4] = [[0.0, 0.0, 0.005], [0.0, 0.0, 0.011], [0.2, 0.1, -1.0], [3.0, 0.0, 1.0]]  # near / behind / aside
    means = (cam_pts - cam.t) @ cam.R  # camera -> world
    quats = rng.standard_normal((n, 4))
    scales = np.exp(rng.uniform(np.log(0.02), np.log(0.5 if dense else 0.25), (n, 3)))
    opac = rng.uniform(0.3, 1.0, n) if dense else rng.uniform(0.0, 1.0, n)
    opac[4] = 0.5 / 255  # below the opacity floor
    feats = rng.standard_normal((n, channels))
    return cam, [means, quats, scales, opac, feats]


CASES = [(seed, w, h, c, dense) for seed in range(3) for (w, h, c) in [(64, 48, 3), (50, 37, 9)]
         for dense in (False, True)]


@pytest.mark.parametrize("seed,width,height,channels,dense", CASES)
def test_matches_oracle(seed, width, height, channels, dense):
    cam, arrays = _scene(seed, width, height, channels, n=150 if dense else 80, dense=dense)
    ref = rasterize_oracle(*arrays, cam)
    out = rasterize(*[torch.tensor(a, dtype=torch.float32) for a in arrays], cam)
    assert isinstance(out, RenderOutput)
    assert out.features.shape == (height, width, channels) and out.alpha.shape == out.depth.shape == (height, width)
    np.testing.assert_allclose(out.features.numpy(), ref[0], atol=1e-4, rtol=0)
    np.testing.assert_allclose(out.alpha.numpy(), ref[1], atol=1e-4, rtol=0)
    np.testing.assert_allclose(out.depth.numpy(), ref[2], atol=1e-4, rtol=2e-5)
    if dense:  # the transmittance stop was exercised
        assert (1 - ref[1]).min() < 2e-4


@pytest.mark.parametrize("seed,width,height,channels,dense", CASES)
def test_matches_numba_splatter(seed, width, height, channels, dense):
    from stg_runtime.splat_cpu import rasterize as rasterize_numba

    cam, arrays = _scene(seed, width, height, channels, n=150 if dense else 80, dense=dense)
    want = rasterize_numba(*[np.asarray(a, np.float32) for a in arrays], cam)
    torch.set_num_threads(1)
    out = rasterize(*[torch.tensor(a, dtype=torch.float32) for a in arrays], cam)
    for got, ref, name in zip(out[:3], want[:3], ("features", "alpha", "depth")):
        np.testing.assert_allclose(got.numpy(), ref, atol=1e-4, rtol=2e-5 if name == "depth" else 0, err_msg=name)


@pytest.mark.parametrize("tile_size,chunk,max_elements", [(16, 64, 1 << 22), (4, 5, 4000), (5, 1, 1 << 22)])
def test_tiling_does_not_change_the_result(tile_size, chunk, max_elements):
    cam, arrays = _scene(1, 50, 37, 3, n=150, dense=True)
    t = [torch.tensor(a, dtype=torch.float64) for a in arrays]
    base = rasterize(*t, cam)
    other = rasterize(*t, cam, tile_size=tile_size, chunk=chunk, max_elements=max_elements)
    for a, b in zip(base, other):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)


def test_float64_matches_reference_exactly():
    cam, arrays = _scene(7, 50, 37, 9, n=150, dense=True)
    ref = rasterize_oracle(*arrays, cam)
    out = rasterize(*[torch.tensor(a, dtype=torch.float64) for a in arrays], cam)
    for got, want in zip(out[:3], ref):
        np.testing.assert_allclose(got.numpy(), want, atol=1e-12, rtol=1e-12)


def test_checkpoint_gives_the_same_values_and_gradients():
    cam, arrays = _scene(2, 50, 37, 3, n=150, dense=True)

    def grads(**kw):
        t = [torch.tensor(a, dtype=torch.float64, requires_grad=True) for a in arrays]
        out = rasterize(*t, cam, **kw)
        (out.features.square().sum() + out.alpha.sum() + out.depth.sum()).backward()
        return [out.features, out.depth] + [x.grad for x in t] + [out.means2d.grad]

    for a, b in zip(grads(), grads(checkpoint=True, max_elements=3000)):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)


def test_no_gaussians():
    cam = _camera(16, 12)
    empty = [torch.zeros(0, 3), torch.zeros(0, 4), torch.zeros(0, 3), torch.zeros(0), torch.zeros(0, 9)]
    out = rasterize(*empty, cam)
    assert out.features.shape == (12, 16, 9) and out.features.abs().max() == 0 and out.depth.abs().max() == 0
    assert out.means2d.shape == (0, 2) and out.radii.shape == (0,)


def test_nothing_visible_still_differentiable():
    cam = _camera(16, 12)
    means = torch.tensor([[0.0, 0.0, -5.0]], requires_grad=True)
    args = [means, torch.tensor([[1.0, 0, 0, 0]]), torch.full((1, 3), 0.1), torch.tensor([0.5]), torch.ones(1, 3)]
    out = rasterize(*args, cam)
    assert out.alpha.abs().max() == 0 and not out.visible.any() and out.radii.tolist() == [0]
    out.features.sum().backward()
    assert means.grad is not None and means.grad.abs().max() == 0


# -- gradients ------------------------------------------------------------------------------------

def _tiny_scene(seed, stop=False):
    """3-5 Gaussians well inside a 16x12 image; alpha stays below 0.99. stop=True stacks near-opaque
    ones so that some pixels hit the transmittance stop."""
    rng = np.random.default_rng(seed)
    cam = Camera.look_at([0, 0, 0], [0, 0, 1], [0, -1, 0], 50.0, 16, 12)
    cam = Camera(cam.fx, cam.fy, cam.cx + 0.6, cam.cy - 0.4, 16, 12, cam.world_to_camera)
    n = 5
    z = rng.uniform(2.0, 3.0, n) if not stop else np.array([2.0, 2.2, 2.4, 2.6, 2.8])
    spread = 0.03 if stop else 0.2
    means = np.stack([rng.uniform(-spread, spread, n) * z, rng.uniform(-spread, spread, n) * 0.75 * z, z], 1)
    quats = rng.standard_normal((n, 4))
    scales = rng.uniform(0.05, 0.2, (n, 3)) if not stop else rng.uniform(0.3, 0.4, (n, 3))
    opac = rng.uniform(0.3, 0.9, n) if not stop else np.array([0.985, 0.98, 0.975, 0.97, 0.965])
    feats = rng.standard_normal((n, 3))
    return cam, [torch.tensor(a, dtype=torch.float64, requires_grad=True) for a in (means, quats, scales, opac, feats)]


@pytest.mark.parametrize("seed,stop", [(0, False), (1, False), (2, True)])
def test_gradcheck(seed, stop, monkeypatch):
    cam, inputs = _tiny_scene(seed, stop)
    if stop:  # the stop rule acts on some pixels of this scene
        with torch.no_grad():
            with_stop = rasterize(*inputs, cam).alpha
            monkeypatch.setattr("stg_train.render.torch_splat.LOG_T_STOP", -math.inf)
            without = rasterize(*inputs, cam).alpha
            monkeypatch.undo()
        assert ((with_stop - without).abs() > 1e-5).sum() >= 3

    def f(*xs):
        out = rasterize(*xs, cam, tile_size=8, chunk=2)
        return out.features, out.alpha, out.depth

    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-6, rtol=1e-4, fast_mode=True)


def _tiny_raw(seed, n=4, static=False):
    rng = np.random.default_rng(seed)
    raw = {
        "xyz": np.stack([rng.uniform(-0.3, 0.3, n), rng.uniform(-0.2, 0.2, n), rng.uniform(2, 3, n)], 1),
        "motion": 0.1 * rng.standard_normal((n, 9)),
        "rotation": rng.standard_normal((n, 4)),
        "omega": 0.3 * rng.standard_normal((n, 4)),
        "log_scale": np.log(rng.uniform(0.05, 0.2, (n, 3))),
        "opacity_logit": rng.uniform(-1, 1.5, (n, 1)),
        "t_center": rng.uniform(0.3, 0.7, n),
        "t_scale_raw": rng.uniform(-1.5, -0.5, n),
        "features": rng.standard_normal((n, 6)),
        "time_features": rng.standard_normal((n, 3)),
    }
    if static:  # nothing but the temporal opacity depends on t_center
        for k in ("motion", "omega", "time_features"):
            raw[k] = np.zeros_like(raw[k])
    return {k: torch.tensor(v, dtype=torch.float64) for k, v in raw.items()}


@pytest.mark.parametrize("static", [False, True])
def test_gradcheck_through_time_evaluation(static):
    """Every raw parameter through params.gaussians_at and rasterize. dt is detached for motion, rotation
    and time features (by design), so t_center is checked only where nothing else depends on it."""
    cam = Camera.look_at([0, 0, 0], [0, 0, 1], [0, -1, 0], 50.0, 16, 12)
    raw = _tiny_raw(3, static=static)
    keys = ["t_center", "t_scale_raw", "opacity_logit"] if static else [k for k in raw if k != "t_center"]

    def f(*xs):
        g = evaluate({**raw, **dict(zip(keys, xs))}, 0.55)
        out = rasterize(*g, cam, tile_size=8)
        return out.features, out.alpha

    inputs = [raw[k].clone().requires_grad_() for k in keys]
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-6, rtol=1e-4, fast_mode=True)


def test_means2d_gradient():
    cam, inputs = _tiny_scene(0)
    means = inputs[0].detach().clone()
    means[0, 2] = -1.0  # behind the camera: culled
    inputs[0] = means.requires_grad_()
    out = rasterize(*inputs, cam)
    assert out.means2d.shape == (5, 2) and out.radii.dtype == torch.int64
    assert out.visible.tolist() == [False, True, True, True, True] and out.radii[0] == 0
    assert (out.radii[1:] > 0).all()
    (out.features ** 2).sum().backward()
    g = out.means2d.grad
    assert g is not None and g.shape == (5, 2)
    assert g[0].abs().max() == 0 and (g[1:].abs().sum(1) > 0).all()
    # The 2D mean enters the image only through the footprint offsets: shifting every pixel-space mean
    # by a small vector changes the loss by about grad . shift.
    with torch.no_grad():
        base = (out.features ** 2).sum()
        h = 1e-6
        shifted = _rasterize_shifted(inputs, cam, torch.tensor([h, -h], dtype=torch.float64))
        assert torch.isclose((shifted - base) / h, g[:, 0].sum() - g[:, 1].sum(), rtol=1e-4, atol=1e-6)


def _rasterize_shifted(inputs, cam, shift):
    """Render with every 2D mean shifted by `shift` pixels: move the principal point by the same amount
    and keep the Jacobian limits (they depend on cx, cy) out of play in this scene."""
    moved = Camera(cam.fx, cam.fy, cam.cx + float(shift[0]), cam.cy + float(shift[1]), cam.width, cam.height,
                   cam.world_to_camera)
    return (rasterize(*inputs, moved).features ** 2).sum()
