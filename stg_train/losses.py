"""The training loss (differentiable, torch): 3DGS's SSIM and (1 - lambda) L1 + lambda (1 - SSIM).

The reported figures (PSNR, SSIM with scikit-image's window, DSSIM) are in stg_train.metrics.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor


def _gauss_1d(size: int, sigma: float, device=None, dtype=None) -> Tensor:
    """(size,) normalised Gaussian weights."""
    x = torch.arange(size, dtype=torch.float64) - size // 2
    g = torch.exp(-x * x / (2 * sigma * sigma))
    return (g / g.sum()).to(device=device, dtype=dtype)


def _blur(t: Tensor, g: Tensor) -> Tensor:
    """t (B, C, H, W) filtered with the window g g^T (g: (K,), K odd), zero padding, same size: a row
    pass then a column pass (the same as one K x K convolution, with 2K instead of K^2 products)."""
    c, k = t.shape[1], g.shape[0]
    t = F.conv2d(t, g.view(1, 1, 1, k).expand(c, 1, 1, k), padding=(0, k // 2), groups=c)
    return F.conv2d(t, g.view(1, 1, k, 1).expand(c, 1, k, 1), padding=(k // 2, 0), groups=c)


def ssim(img: Tensor, ref: Tensor, window: int = 11, sigma: float = 1.5) -> Tensor:
    """Mean SSIM of images (B, H, W, 3) in [0, 1], 3DGS's version (Gaussian window, zero padding)."""
    x, y = img.permute(0, 3, 1, 2), ref.permute(0, 3, 1, 2)
    c = x.shape[1]
    g = _gauss_1d(window, sigma, x.device, x.dtype)
    # The five local means, in two filtering passes: x, x^2, xy (differentiated) and y, y^2 (the
    # reference: no gradient, so the backward pass filters 9 channels, not 15).
    mu_x, exx, exy = _blur(torch.cat([x, x * x, x * y], 1), g).split(c, 1)
    mu_y, eyy = _blur(torch.cat([y, y * y], 1), g).split(c, 1)
    sxx, syy, sxy = exx - mu_x * mu_x, eyy - mu_y * mu_y, exy - mu_x * mu_y
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    s = ((2 * mu_x * mu_y + c1) * (2 * sxy + c2)) / ((mu_x ** 2 + mu_y ** 2 + c1) * (sxx + syy + c2))
    return s.mean()


def loss_fn(img: Tensor, ref: Tensor, lambda_dssim: float = 0.2) -> Tensor:
    """(1 - lambda) L1 + lambda (1 - SSIM) over a batch (B, H, W, 3)."""
    return (1 - lambda_dssim) * (img - ref).abs().mean() + lambda_dssim * (1 - ssim(img, ref))
