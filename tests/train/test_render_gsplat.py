"""The gsplat backend of stg_train.render.rasterize: backend selection, the adapter's mapping of our
inputs and outputs onto gsplat's `rasterization()` contract (on the CPU, through a stand-in that checks
the contract and renders with our torch splatter), and the real thing where gsplat and CUDA exist."""
from __future__ import annotations

import sys
import types

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from stg_runtime.camera import Camera  # noqa: E402
from stg_train.render import gsplat_backend  # noqa: E402
from stg_train.render import RenderOutput, rasterize, resolve_backend  # noqa: E402
from stg_train.strategy import DensityControl, Schedule  # noqa: E402


def _scene(n=60, channels=9, seed=0, device="cpu"):
    g = torch.Generator().manual_seed(seed)
    means = torch.rand(n, 3, generator=g) * torch.tensor([2.0, 1.5, 2.0]) - torch.tensor([1.0, 0.75, -2.0])
    quats = torch.randn(n, 4, generator=g)
    scales = torch.rand(n, 3, generator=g) * 0.15 + 0.02
    opacities = torch.rand(n, generator=g) * 0.9 + 0.05
    features = torch.rand(n, channels, generator=g)
    means[:5, 2] = -1.0  # behind the camera: culled
    camera = Camera.look_at(eye=[0.1, -0.2, 0.0], target=[0, 0, 3], up=[0, -1, 0], fov_deg=55, width=40, height=30)
    return [t.to(device) for t in (means, quats, scales, opacities, features)], camera


def _stand_in(calls: list):
    """gsplat.rasterization as its docstring specifies it (packed=False, one camera, N-D colours,
    render_mode "RGB+ED"), computed with our torch splatter from the camera it is given."""

    def rasterization(means, quats, scales, opacities, colors, viewmats, Ks, width, height, *, near_plane,
                      eps2d, packed, render_mode, rasterize_mode, camera_model="pinhole", **rest):
        n = means.shape[0]
        assert means.shape == (n, 3) and quats.shape == (n, 4) and scales.shape == (n, 3)
        assert opacities.shape == (n,) and colors.shape[0] == n and colors.dim() == 2
        assert viewmats.shape == (1, 4, 4) and Ks.shape == (1, 3, 3)
        assert (near_plane, eps2d, packed, render_mode, rasterize_mode) == (0.01, 0.3, False, "RGB+ED", "classic")
        assert camera_model in ("pinhole", "fisheye") and "radial_coeffs" not in rest and not rest.get("with_ut")
        calls.append(camera_model)
        cam = Camera.from_colmap(Ks[0].numpy(), viewmats[0].numpy(), width, height)
        if camera_model == "fisheye":  # gsplat's EWA fisheye: the equidistant model
            cam = Camera(cam.fx, cam.fy, cam.cx, cam.cy, width, height, cam.world_to_camera, model="fisheye")
        out = rasterize(means, quats, scales, opacities, colors, cam)
        render = torch.cat([out.features, out.depth[..., None]], -1)[None]  # (1, H, W, D + 1)
        radii = out.radii[None, :, None].expand(1, n, 2).to(torch.int32)  # gsplat >= 1.5: per axis
        return render, out.alpha[None, ..., None], {"means2d": out.means2d[None], "radii": radii}

    return rasterization


def test_adapter_maps_inputs_and_outputs_like_the_torch_backend():
    (means, quats, scales, opacities, features), camera = _scene()
    calls = []
    got = gsplat_backend.rasterize_gsplat(means, quats, scales, opacities, features, camera,
                                        rasterization=_stand_in(calls))
    want = rasterize(means, quats, scales, opacities, features, camera)
    assert calls == ["pinhole"] and isinstance(got, RenderOutput)
    assert got.features.shape == (30, 40, 9) and got.alpha.shape == (30, 40) and got.depth.shape == (30, 40)
    assert torch.equal(got.features, want.features) and torch.equal(got.alpha, want.alpha)
    assert torch.equal(got.depth, want.depth)
    assert torch.equal(got.radii, want.radii) and torch.equal(got.visible, want.visible)
    assert got.visible.any() and not got.visible.all()  # the scene has culled and drawn Gaussians
    assert got.means2d.shape == (1, 60, 2)


def _fisheye(distortion=(0.0, 0.0, 0.0, 0.0)):
    base = Camera.look_at(eye=[0.1, -0.2, 0.0], target=[0, 0, 3], up=[0, -1, 0], fov_deg=150, width=40, height=30,
                          model="fisheye")
    return Camera(base.fx, base.fy, base.cx + 0.5, base.cy, 40, 30, base.world_to_camera, "f", "fisheye", distortion)


@pytest.mark.parametrize("distortion,gsplat_draws", [((0.0, 0.0, 0.0, 0.0), True), ((0.02, -0.01, 0.0, 0.001), False)])
def test_fisheye_goes_to_gsplat_only_without_distortion(distortion, gsplat_draws):
    """An equidistant fisheye is gsplat's EWA camera_model "fisheye"; one with k1..k4 (which gsplat's EWA
    path lacks) is drawn by the torch splatter. Either way the result is the torch splatter's."""
    (means, quats, scales, opacities, features), _ = _scene()
    camera = _fisheye(distortion)
    assert gsplat_backend.covers(camera) == gsplat_draws
    calls = []
    got = gsplat_backend.rasterize_gsplat(means, quats, scales, opacities, features, camera,
                                        rasterization=_stand_in(calls))
    want = rasterize(means, quats, scales, opacities, features, camera)
    assert calls == (["fisheye"] if gsplat_draws else [])
    for a, b in zip(got, want):
        if a.shape != b.shape:  # gsplat's batched means2d
            a = a[0]
        assert torch.equal(a, b)
    assert want.visible.sum() > 10


def test_ewa_fisheye_of_gsplat_is_ours_without_distortion():
    """gsplat's torch reference of its EWA fisheye projection (where gsplat is installed) against our
    projection of an equidistant fisheye: the same 2D means and covariances up to its 1e-7 epsilons."""
    try:
        from gsplat.cuda._torch_impl import _fisheye_proj, _quat_scale_to_covar_preci
    except ImportError:
        pytest.skip("needs gsplat (its torch reference implementation)")
    from stg_train.render.torch_splat import project

    (means, quats, scales, opacities, _), _ = _scene(n=200)
    camera = _fisheye()
    means, quats, scales = (t.double() for t in (means, quats, scales))
    p = project(means, quats, scales, torch.ones(200, dtype=torch.float64), camera)
    A, B, C = p.conic[p.valid].unbind(-1)
    det = A * C - B * B
    ours = torch.stack([C / det - 0.3, -B / det, A / det - 0.3], -1)
    R, t = torch.tensor(camera.R), torch.tensor(camera.t)
    covars, _ = _quat_scale_to_covar_preci(quats, scales, compute_preci=False, triu=False)
    m2, c2 = _fisheye_proj((means @ R.T + t)[None], (R @ covars @ R.T)[None], torch.tensor(camera.K)[None], 40, 30)
    m2, c2 = m2[0][p.valid], c2[0][p.valid]
    theirs = torch.stack([c2[:, 0, 0], c2[:, 0, 1], c2[:, 1, 1]], -1)
    assert p.valid.sum() > 100
    torch.testing.assert_close(m2, p.means2d[p.valid], rtol=0, atol=1e-4)
    torch.testing.assert_close(theirs, ours, rtol=1e-5, atol=1e-5 * float(ours.abs().max()))


def test_density_control_reads_batched_screen_gradients():
    """The gsplat backend's means2d is (1, M, 2): its gradient must count as the (M, 2) one does."""
    (means, quats, scales, opacities, features), camera = _scene(n=20)
    out = rasterize(means.requires_grad_(), quats, scales, opacities, features, camera)
    out.features.sum().backward()
    grad = out.means2d.grad
    batched = torch.zeros(1, 20, 2, requires_grad=True)
    batched.grad = grad[None].clone()
    sched = Schedule.scaled(1000)
    a, b = DensityControl(sched, 1.0), DensityControl(sched, 1.0)
    a.accumulate([(camera, out)], 0.5)
    b.accumulate([(camera, out._replace(means2d=batched))], 0.5)
    assert torch.equal(a.grad_sum, b.grad_sum) and torch.equal(a.grad_count, b.grad_count)
    assert (a.grad_sum > 0).any()


def test_backend_selection(monkeypatch):
    monkeypatch.setitem(sys.modules, "gsplat", None)  # not installed
    assert resolve_backend("auto", "cpu") == "numba"
    assert resolve_backend("auto", "cuda") == "torch"
    assert resolve_backend("torch", "cuda") == "torch"
    with pytest.raises(ValueError, match="not installed"):
        resolve_backend("gsplat", "cuda")
    monkeypatch.setitem(sys.modules, "gsplat", types.ModuleType("gsplat"))  # installed
    with pytest.raises(ValueError, match="--device cuda"):
        resolve_backend("gsplat", "cpu")
    assert resolve_backend("auto", "cpu") == "numba"
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="no CUDA device"):
            resolve_backend("gsplat", "cuda")
    with pytest.raises(ValueError, match="backend"):
        rasterize(*_scene()[0], _scene()[1], backend="opengl")


def _gsplat_on_cuda() -> bool:
    try:
        import gsplat  # noqa: F401
    except ImportError:
        return False
    return torch.cuda.is_available()


@pytest.mark.skipif(not _gsplat_on_cuda(), reason="needs gsplat and a CUDA device")
def test_gsplat_fisheye_matches_the_torch_backend_on_cuda():
    """gsplat's EWA fisheye (equidistant) against the torch splatter, as for pinholes below."""
    (means, quats, scales, opacities, features), _ = _scene(n=400, device="cuda")
    camera = _fisheye()
    means.requires_grad_()
    got = rasterize(means, quats, scales, opacities, features, camera, backend="gsplat")
    want = rasterize(means, quats, scales, opacities, features, camera, backend="torch")
    assert got.means2d.shape == (1, 400, 2)  # drawn by gsplat, not by the fallback
    for a, b in ((got.features, want.features), (got.alpha, want.alpha), (got.depth, want.depth)):
        diff = (a - b).abs().detach().cpu().numpy()
        assert np.mean(diff > 1e-3) < 1e-3 and diff.max() < 0.05
    got.features.sum().backward()
    assert means.grad is not None and torch.isfinite(means.grad).all()


@pytest.mark.skipif(not _gsplat_on_cuda(), reason="needs gsplat and a CUDA device")
def test_gsplat_matches_the_torch_backend_on_cuda():
    (means, quats, scales, opacities, features), camera = _scene(n=400, device="cuda")
    means.requires_grad_()
    got = rasterize(means, quats, scales, opacities, features, camera, backend="gsplat")
    want = rasterize(means, quats, scales, opacities, features, camera, backend="torch")
    for a, b in ((got.features, want.features), (got.alpha, want.alpha), (got.depth, want.depth)):
        diff = (a - b).abs().detach().cpu().numpy()
        assert np.mean(diff > 1e-3) < 1e-3 and diff.max() < 0.05
    got.features.sum().backward()
    assert got.means2d.grad is not None and got.means2d.grad.shape == (1, 400, 2)
    assert means.grad is not None and torch.isfinite(means.grad).all()
