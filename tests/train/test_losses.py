"""The training loss: the separable SSIM against a direct 11x11-window transcription of 3DGS's SSIM."""
import pytest

torch = pytest.importorskip("torch")
import torch.nn.functional as F  # noqa: E402

from stg_train.losses import loss_fn, ssim  # noqa: E402


def _ssim_direct(x, y, size=11, sigma=1.5):
    """3DGS's SSIM, as written there: five depthwise convolutions with the 2D Gaussian window."""
    x, y = x.permute(0, 3, 1, 2), y.permute(0, 3, 1, 2)
    r = torch.arange(size, dtype=x.dtype) - size // 2
    g = torch.exp(-r * r / (2 * sigma * sigma))
    g = g / g.sum()
    w = (g[:, None] * g[None, :]).expand(3, 1, size, size)
    conv = lambda t: F.conv2d(t, w, padding=size // 2, groups=3)  # noqa: E731
    mx, my = conv(x), conv(y)
    sxx, syy, sxy = conv(x * x) - mx * mx, conv(y * y) - my * my, conv(x * y) - mx * my
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    return (((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx ** 2 + my ** 2 + c1) * (sxx + syy + c2))).mean()


def test_ssim_matches_the_direct_window_with_its_gradient():
    gen = torch.Generator().manual_seed(0)
    ref = torch.rand(2, 37, 50, 3, generator=gen, dtype=torch.float64)
    img = (ref + 0.2 * torch.rand(ref.shape, generator=gen, dtype=torch.float64)).clamp(0, 1)
    a, b = img.clone().requires_grad_(), img.clone().requires_grad_()
    got, want = ssim(a, ref), _ssim_direct(b, ref)
    got.backward()
    want.backward()
    got, want = float(got.detach()), float(want.detach())
    assert got == pytest.approx(want, abs=1e-12) and 0.3 < got < 0.99
    torch.testing.assert_close(a.grad, b.grad, rtol=1e-9, atol=1e-15)
    assert float(ssim(ref, ref)) == pytest.approx(1.0, abs=1e-12)


def test_loss_is_zero_only_for_equal_images():
    gen = torch.Generator().manual_seed(1)
    ref = torch.rand(1, 20, 24, 3, generator=gen)
    assert float(loss_fn(ref, ref)) == pytest.approx(0.0, abs=1e-6)
    assert float(loss_fn(ref.flip(1), ref)) > 0.1
