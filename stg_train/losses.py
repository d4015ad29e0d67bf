"""The training loss (differentiable, torch): 3DGS's SSIM and (1 - lambda) L1 + lambda (1 - SSIM).

The reported figures (PSNR, SSIM with scikit-image's window, DSSIM) are in stg_train.metrics.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor


def _gauss_window(size: int = 11, sigma: float = 1.5, channels: int = 3, device=None, dtype=None) -> Tensor:
    x = torch.arange(size, dtype=torch.float64) - size // 2
    g = torch.exp(-x * x / (2 * sigma * sigma))
    g = (g / g.sum()).to(device=device, dtype=dtype)
    return (g[:, None] * g[None, :]).expand(channels, 1, size, size).contiguous()


def ssim(img: Tensor, ref: Tensor, window: int = 11, sigma: float = 1.5) -> Tensor:
    """Mean SSIM of images (B, H, W, 3) in [0, 1], 3DGS's version (Gaussian window, zero padding)."""
    x, y = img.permute(0, 3, 1, 2), ref.permute(0, 3, 1, 2)
    c = x.shape[1]
    w = _gauss_window(window, sigma, c, x.device, x.dtype)
    pad = window // 2
    mu_x, mu_y = F.conv2d(x, w, padding=pad, groups=c), F.conv2d(y, w, padding=pad, groups=c)
    sxx = F.conv2d(x * x, w, padding=pad, groups=c) - mu_x * mu_x
    syy = F.conv2d(y * y, w, padding=pad, groups=c) - mu_y * mu_y
    sxy = F.conv2d(x * y, w, padding=pad, groups=c) - mu_x * mu_y
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    s = ((2 * mu_x * mu_y + c1) * (2 * sxy + c2)) / ((mu_x ** 2 + mu_y ** 2 + c1) * (sxx + syy + c2))
    return s.mean()


def loss_fn(img: Tensor, ref: Tensor, lambda_dssim: float = 0.2) -> Tensor:
    """(1 - lambda) L1 + lambda (1 - SSIM) over a batch (B, H, W, 3)."""
    return (1 - lambda_dssim) * (img - ref).abs().mean() + lambda_dssim * (1 - ssim(img, ref))
