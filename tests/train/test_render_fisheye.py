"""Fisheye cameras in the trainer's splatters (formats/stg-v1.md sections 1 and 3): the torch splatter
against the float64 oracle on random fisheye scenes of 120 to 200 degrees, the numba training splatter
against the torch splatter (images and every gradient, float64), finite differences, and the culls at
and beyond 90 degrees off the axis and at a camera's max_angle (zero, finite gradients)."""
import numpy as np
import pytest

torch = pytest.importorskip("torch")

from stg_runtime.camera import Camera  # noqa: E402
from stg_runtime.spec import project_oracle, rasterize_oracle  # noqa: E402
from stg_train.render import rasterize  # noqa: E402
from stg_train.render.torch_splat import project  # noqa: E402

from ..scenes import clean_scenes, random_scene  # noqa: E402
from .test_render_numba import _outputs_and_grads, _tensors  # noqa: E402

NAMES = ("means", "quats", "scales", "opacities", "features", "means2d")


@pytest.fixture(autouse=True)
def _one_thread():
    """Small tensors: threads only add contention on shared CI cores."""
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


def _narrow_fisheye(width=40, height=32):
    """A fisheye whose distortion stops increasing at about 57 degrees (k1 = -0.35): its max_angle cull
    acts in front of the camera (z > 0), unlike the near plane."""
    base = Camera.look_at([0.1, 0.0, -0.2], [0.2, -0.1, 3.0], [0, -1, 0], 90.0, width, height, model="fisheye")
    cam = Camera(base.fx, base.fy * 1.05, base.cx + 1.3, base.cy - 0.8, width, height, base.world_to_camera,
                 "narrow", "fisheye", (-0.35, 0.02, 0.0, 0.0))
    assert 0.9 < cam.max_angle < 1.1
    return cam


def _angle_scene(cam, angles_deg, seed=0, channels=3):
    """Gaussians at the given angles off the axis (degrees) in random directions around it, 1.5 to 3
    units away, sized a few pixels, plus two exactly on the axis (r = 0)."""
    rng = np.random.default_rng(seed)
    theta = np.radians(np.concatenate([[0.0, 0.0], angles_deg]))
    n = len(theta)
    phi = rng.uniform(0, 2 * np.pi, n)
    dist = rng.uniform(1.5, 3.0, n)
    p_cam = dist[:, None] * np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], 1)
    means = (p_cam - cam.t) @ cam.R
    quats = rng.standard_normal((n, 4))
    scales = dist[:, None] / cam.fx * rng.uniform(1.0, 4.0, (n, 3))
    opac = rng.uniform(0.3, 0.9, n)
    feats = rng.standard_normal((n, channels))
    return [means, quats, scales, opac, feats]


@pytest.mark.parametrize("hfov", [120, 180, 200])
def test_torch_splatter_matches_the_oracle(hfov):
    """float64: the oracle's images to 1e-12; float32: to 1e-4 (scenes whose decisions are clear of
    float32 rounding); the 2D means of the visible Gaussians and the culls are the oracle's."""
    for arrays, cam, ref in clean_scenes(hfov, 2, 150, 48, 40, 3, fisheye=hfov):
        out = rasterize(*_tensors(arrays), cam, backend="torch")
        for got, want in zip(out[:3], ref):
            np.testing.assert_allclose(got.numpy(), want, atol=1e-12, rtol=1e-12)
        proj = project_oracle(*arrays[:3], cam)
        p = project(*_tensors(arrays[:4]), cam)
        assert torch.equal(p.valid, torch.as_tensor(proj.visible & (arrays[3] >= 1 / 255)))
        np.testing.assert_allclose(p.means2d.numpy()[proj.visible], proj.mean2d[proj.visible], rtol=0, atol=1e-9)
        np.testing.assert_allclose(p.radius.numpy()[p.valid.numpy()], proj.radius[p.valid.numpy()])
        out32 = rasterize(*[torch.tensor(a) for a in arrays], cam, backend="torch")
        for got, want in zip(out32[:3], ref):
            np.testing.assert_allclose(got.numpy(), want, atol=1e-4, rtol=2e-5)
        assert out.alpha.max() > 0.5  # something is drawn


def test_max_angle_cull_matches_the_oracle():
    """Gaussians straddling a narrow fisheye's max_angle (57 degrees), in front of the camera: the same
    culls and images as the oracle; the culled ones get zero, finite gradients."""
    cam = _narrow_fisheye()
    rng = np.random.default_rng(4)
    arrays = _angle_scene(cam, np.concatenate([rng.uniform(0, 50, 30), rng.uniform(54, 62, 20)]))
    ref = rasterize_oracle(*arrays, cam)
    proj = project_oracle(*arrays[:3], cam)
    theta = np.arctan2(np.hypot(*(arrays[0] @ cam.R.T + cam.t)[:, :2].T), (arrays[0] @ cam.R.T + cam.t)[:, 2])
    assert not proj.visible[theta >= cam.max_angle].any() and (theta >= cam.max_angle).sum() >= 5
    for backend in ("torch", "numba"):
        out, grads = _outputs_and_grads(arrays, cam, backend)
        for got, want in zip(out[:3], ref):
            np.testing.assert_allclose(got.detach().numpy(), want, atol=1e-12, rtol=1e-12)
        culled = torch.as_tensor(theta >= cam.max_angle)
        for g, name in zip(grads[:3], NAMES):
            assert torch.isfinite(g).all(), name
            assert g[culled].abs().max() == 0, name
        assert grads[0][~culled].abs().max() > 0


@pytest.mark.parametrize("seed,hfov", [(0, 120), (1, 180), (2, 200)])
def test_numba_splatter_matches_the_torch_splatter(seed, hfov):
    """Images and every gradient, float64, on random fisheye scenes with Gaussians up to 100 degrees off
    the axis (a tenth between 85 and 95): those beyond 90 degrees are culled, with zero gradients."""
    rng = np.random.default_rng(seed)
    arrays, cam = random_scene(rng, 200, 48, 40, 9, fisheye=hfov)
    out, grads = _outputs_and_grads(arrays, cam, "numba")
    ref, ref_grads = _outputs_and_grads(arrays, cam, "torch")
    for got, want in zip(out[:3], ref[:3]):
        np.testing.assert_allclose(got.detach().numpy(), want.detach().numpy(), atol=1e-12, rtol=1e-12)
    assert torch.equal(out.visible, ref.visible) and torch.equal(out.radii, ref.radii)
    for got, want, name in zip(grads, ref_grads, NAMES):
        assert torch.isfinite(got).all(), name
        torch.testing.assert_close(got, want, rtol=1e-9, atol=1e-9 * float(want.abs().max()), msg=name)
    z = (np.asarray(arrays[0], np.float64) @ cam.R.T + cam.t)[:, 2]
    behind = torch.as_tensor(z <= 0.01)
    assert behind.sum() >= 5 and not out.visible[behind].any()
    for g, name in zip(grads[:5], NAMES):
        assert g[behind].abs().max() == 0, name
    assert out.visible.sum() >= 50


@pytest.mark.parametrize("hfov", [120, 180, 200])
def test_numba_float32_matches_the_runtime_splatter(hfov):
    """The golden images: the trainer's float32 forward pass through a fisheye draws what the Player's
    splatter draws."""
    from stg_runtime.splat_cpu import rasterize as rasterize_runtime

    for arrays, cam, _ in clean_scenes(hfov + 7, 2, 150, 48, 40, 3, fisheye=hfov):
        want = rasterize_runtime(*arrays, cam)
        out = rasterize(*[torch.tensor(a) for a in arrays], cam, backend="numba")
        for got, ref, name in zip(out[:3], want, ("features", "alpha", "depth")):
            np.testing.assert_allclose(got.numpy(), ref, atol=1e-4, rtol=2e-5 if name == "depth" else 0, err_msg=name)


@pytest.mark.parametrize("backend", ["torch", "numba"])
def test_gradcheck(backend):
    """Finite differences in float64 on a small distorted fisheye scene: Gaussians on the axis (r = 0),
    off it, near 90 degrees and behind the image plane."""
    base = Camera.look_at([0, 0, 0], [0, 0, 1], [0, -1, 0], 190.0, 20, 16, model="fisheye")
    cam = Camera(base.fx, base.fy, base.cx + 0.4, base.cy - 0.3, 20, 16, base.world_to_camera, "g", "fisheye",
                 (0.03, -0.004, 0.001, -0.0002))
    arrays = _angle_scene(cam, [25.0, 50.0, 80.0, 88.0, 93.0], seed=3)
    arrays[2] = arrays[2] * 2.0  # a few pixels wide at 20x16
    inputs = _tensors(arrays, grad=True)

    def f(*xs):
        out = rasterize(*xs, cam, backend=backend)
        return out.features, out.alpha, out.depth

    with torch.no_grad():
        drawn = f(*inputs)[1]
    assert drawn.max() > 0.2
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-6, rtol=1e-4, fast_mode=True)


def test_gaussian_on_the_axis_has_the_limit_gradient():
    """At r = 0 exactly, d(means2d)/d(means) is the axis limit diag(fx, fy) / z (no NaN from sqrt or atan2),
    equal to a central difference taken off the axis."""
    cam = Camera.look_at([0, 0, 0], [0, 0, 1], [0, -1, 0], 180.0, 32, 24, model="fisheye")
    cam = Camera(cam.fx, cam.fy, cam.cx, cam.cy, 32, 24, cam.world_to_camera, "", "fisheye", (0.05, 0.0, 0.0, 0.0))
    args = _tensors([[[0.0, 0.0, 2.0]], [[1.0, 0.0, 0.0, 0.0]], [[0.1, 0.1, 0.1]], [0.5]])
    args[0].requires_grad_()
    jac = torch.autograd.functional.jacobian(lambda m: project(m, *args[1:], cam).means2d, args[0])[0, :, 0, :]
    assert torch.isfinite(jac).all()
    torch.testing.assert_close(jac[:, :2], torch.tensor([[cam.fx / 2, 0.0], [0.0, cam.fy / 2]], dtype=torch.float64),
                               rtol=1e-12, atol=1e-12)
    conic_grad = torch.autograd.grad(project(*args, cam).conic.sum(), args[0])[0]
    assert torch.isfinite(conic_grad).all()
    eps = 1e-5
    shifted = [project(args[0].detach() + torch.tensor([[s * eps, 0.0, 0.0]], dtype=torch.float64), *args[1:], cam)
               for s in (1, -1)]
    fd = (shifted[0].means2d - shifted[1].means2d)[0] / (2 * eps)
    torch.testing.assert_close(jac[:, 0], fd, rtol=1e-8, atol=1e-8)


@pytest.mark.parametrize("backend", ["torch", "numba"])
def test_degenerate_culled_points_have_zero_finite_gradients(backend):
    """Culled Gaussians where the fisheye formulas have no value (on the axis behind the camera, at the
    camera centre, in the image plane z = 0) next to a drawn one: finite images, zero gradients."""
    cam = Camera.look_at([0, 0, 0], [0, 0, 1], [0, -1, 0], 200.0, 24, 20, model="fisheye")
    cam = Camera(cam.fx, cam.fy, cam.cx, cam.cy, 24, 20, cam.world_to_camera, "", "fisheye", (0.02, 0.0, 0.0, 0.0))
    p_cam = np.array([[0.0, 0.0, -2.0], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, -1e-9, 0.0], [0.1, 0.2, 2.0]])
    n = len(p_cam)
    arrays = [(p_cam - cam.t) @ cam.R, np.tile([1.0, 0.2, -0.1, 0.3], (n, 1)), np.full((n, 3), 0.2),
              np.full(n, 0.8), np.ones((n, 3))]
    out, grads = _outputs_and_grads(arrays, cam, backend)
    assert out.visible.tolist() == [False] * 4 + [True]
    assert all(torch.isfinite(x).all() for x in (*out[:3], out.means2d))
    for g, name in zip(grads, NAMES):
        assert torch.isfinite(g).all(), name
        assert g[:4].abs().max() == 0, name
    assert grads[0][4].abs().max() > 0
