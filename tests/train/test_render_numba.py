"""The numba CPU training splatter (stg_train.render.numba_splat): its images against the float64
oracle, the torch splatter and the runtime's splatter; its gradients against the torch splatter's
autograd and against finite differences, in float64."""
import numpy as np
import pytest

torch = pytest.importorskip("torch")

from stg_runtime.camera import Camera  # noqa: E402
from stg_runtime.spec import rasterize_oracle  # noqa: E402
from stg_train.render import RenderOutput, rasterize, resolve_backend  # noqa: E402

from .test_render_torch import CASES, _camera, _scene, _tiny_scene  # noqa: E402


def _tensors(arrays, dtype=torch.float64, grad=False):
    return [torch.tensor(a, dtype=dtype, requires_grad=grad) for a in arrays]


def _outputs_and_grads(arrays, cam, backend, seed=1):
    """Images, then the gradients of a random linear function of all three images w.r.t. every input
    and means2d."""
    inputs = _tensors(arrays, grad=True)
    out = rasterize(*inputs, cam, backend=backend)
    gen = torch.Generator().manual_seed(seed)
    loss = sum((img * torch.randn(img.shape, generator=gen, dtype=img.dtype)).sum()
               for img in (out.features, out.alpha, out.depth))
    loss.backward()
    return out, [x.grad for x in inputs] + [out.means2d.grad]


def _border_scene(seed=0, n=40):
    """Overlapping, mostly nearly opaque Gaussians whose centres sit on the 16-pixel tile borders of a
    48x40 image, so that footprints straddle tiles and many pixels reach the transmittance stop."""
    rng = np.random.default_rng(seed)
    cam = Camera.look_at([0, 0, 0], [0, 0, 1], [0, -1, 0], 60.0, 48, 40)
    u = rng.choice([16.0, 32.0], n) + rng.uniform(-1.5, 1.5, n)
    v = rng.choice([16.0, 24.0], n) + rng.uniform(-1.5, 1.5, n)
    z = rng.uniform(2.0, 4.0, n)
    means = np.stack([(u - cam.cx) / cam.fx * z, (v - cam.cy) / cam.fy * z, z], 1)
    quats = rng.standard_normal((n, 4))
    scales = rng.uniform(0.05, 0.25, (n, 3))
    opac = np.where(rng.uniform(size=n) < 0.7, rng.uniform(0.9, 0.999, n), rng.uniform(0.1, 0.9, n))
    feats = rng.standard_normal((n, 9))
    return cam, [means, quats, scales, opac, feats]


#: Beside CASES' 3 and 9 channels: channel counts that are not a multiple of three (the kernels take
#: channels three at a time, the first three in the main loop).
ODD_CHANNELS = [(3, 40, 30, 1, True), (4, 40, 30, 5, False), (5, 33, 21, 13, True)]


@pytest.mark.parametrize("seed,width,height,channels,dense", CASES + ODD_CHANNELS)
def test_matches_oracle_and_torch_splatter(seed, width, height, channels, dense):
    cam, arrays = _scene(seed, width, height, channels, n=150 if dense else 80, dense=dense)
    ref = rasterize_oracle(*arrays, cam)
    out, grads = _outputs_and_grads(arrays, cam, "numba")
    assert isinstance(out, RenderOutput)
    assert out.features.shape == (height, width, channels) and out.alpha.shape == out.depth.shape == (height, width)
    for got, want in zip(out[:3], ref):
        np.testing.assert_allclose(got.detach().numpy(), want, atol=1e-12, rtol=1e-12)
    ref_out, ref_grads = _outputs_and_grads(arrays, cam, "torch")
    assert torch.equal(out.visible, ref_out.visible) and torch.equal(out.radii, ref_out.radii)
    names = ("means", "quats", "scales", "opacities", "features", "means2d")
    for got, want, name in zip(grads, ref_grads, names):
        torch.testing.assert_close(got, want, rtol=1e-9, atol=1e-9 * float(want.abs().max()), msg=name)


def test_gradients_at_tile_borders_with_the_stop():
    cam, arrays = _border_scene()
    ref = rasterize_oracle(*arrays, cam)
    assert (1 - ref[1]).min() < 2e-4  # the transmittance stop acts
    out, grads = _outputs_and_grads(arrays, cam, "numba", seed=3)
    ref_out, ref_grads = _outputs_and_grads(arrays, cam, "torch", seed=3)
    for got, want in zip(grads, ref_grads):
        torch.testing.assert_close(got, want, rtol=1e-9, atol=1e-9 * float(want.abs().max()))


@pytest.mark.parametrize("seed,stop", [(0, False), (1, False), (2, True)])
def test_gradcheck(seed, stop):
    """Finite differences in float64 for every parameter kind (means, quats, scales, opacities,
    features), with the transmittance stop acting in the third scene."""
    cam, inputs = _tiny_scene(seed, stop)

    def f(*xs):
        out = rasterize(*xs, cam, backend="numba")
        return out.features, out.alpha, out.depth

    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-6, rtol=1e-4, fast_mode=True)


def test_gradcheck_nearly_opaque_overlaps():
    """Finite differences on Gaussians that overlap, straddle tile borders and reach the stop (a smaller
    copy of _border_scene, every input checked)."""
    cam, arrays = _border_scene(seed=5, n=12)
    inputs = _tensors(arrays, grad=True)

    def f(*xs):
        out = rasterize(*xs, cam, backend="numba")
        return out.features, out.alpha, out.depth

    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=True)


@pytest.mark.parametrize("seed,width,height,channels,dense", CASES[::3])
def test_float32_matches_the_runtime_splatter(seed, width, height, channels, dense):
    """The golden images: the trainer's float32 forward pass draws what the Player's splatter draws."""
    from stg_runtime.splat_cpu import rasterize as rasterize_runtime

    cam, arrays = _scene(seed, width, height, channels, n=150 if dense else 80, dense=dense)
    want = rasterize_runtime(*[np.asarray(a, np.float32) for a in arrays], cam)
    out = rasterize(*_tensors(arrays, torch.float32), cam, backend="numba")
    for got, ref, name in zip(out[:3], want, ("features", "alpha", "depth")):
        np.testing.assert_allclose(got.numpy(), ref, atol=1e-4, rtol=2e-5 if name == "depth" else 0, err_msg=name)


def test_gradients_are_reproducible_whatever_the_threads():
    """float32 gradients are the same bits in every run, on one thread as on two (the per-Gaussian sums
    are taken in a fixed order, not by thread)."""
    import numba
    cam, arrays = _scene(4, 64, 48, 9, n=300, dense=True)
    arrays = [np.asarray(a, np.float32) for a in arrays]
    threads = numba.get_num_threads()
    first = _outputs_and_grads(arrays, cam, "numba")[1]
    second = _outputs_and_grads(arrays, cam, "numba")[1]
    numba.set_num_threads(1)
    try:
        single = _outputs_and_grads(arrays, cam, "numba")[1]
    finally:
        numba.set_num_threads(threads)
    for a, b, c in zip(first, second, single):
        assert torch.equal(a, b) and torch.equal(a, c)


def test_only_image_outputs_used():
    """A loss on the features alone (no alpha or depth gradient) matches the torch splatter."""
    cam, arrays = _scene(0, 50, 37, 3, n=150, dense=True)
    grads = []
    for backend in ("numba", "torch"):
        inputs = _tensors(arrays, grad=True)
        rasterize(*inputs, cam, backend=backend).features.square().sum().backward()
        grads.append([x.grad for x in inputs])
    for got, want in zip(*grads):
        torch.testing.assert_close(got, want, rtol=1e-9, atol=1e-9 * float(want.abs().max()))


def test_no_gaussians_and_nothing_visible():
    cam = _camera(16, 12)
    empty = [torch.zeros(0, 3), torch.zeros(0, 4), torch.zeros(0, 3), torch.zeros(0), torch.zeros(0, 9)]
    out = rasterize(*empty, cam, backend="numba")
    assert out.features.shape == (12, 16, 9) and out.features.abs().max() == 0 and out.depth.abs().max() == 0
    means = torch.tensor([[0.0, 0.0, -5.0]], requires_grad=True)
    args = [means, torch.tensor([[1.0, 0, 0, 0]]), torch.full((1, 3), 0.1), torch.tensor([0.5]), torch.ones(1, 3)]
    out = rasterize(*args, cam, backend="numba")
    assert out.alpha.abs().max() == 0 and not out.visible.any() and out.radii.tolist() == [0]
    out.features.sum().backward()
    assert means.grad is not None and means.grad.abs().max() == 0


def test_backend_choice():
    assert resolve_backend("auto", "cpu") == "numba"
    assert resolve_backend("numba", "cpu") == "numba"
    assert resolve_backend("torch", "cpu") == "torch"
    with pytest.raises(ValueError, match="runs on the CPU"):
        resolve_backend("numba", "cuda")
    with pytest.raises(ValueError, match="splatter must be"):
        resolve_backend("fast", "cpu")
