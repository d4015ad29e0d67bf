"""The result of a differentiable render, the same for every backend of stg_train.render."""
from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor


class RenderOutput(NamedTuple):
    """What stg_train.render.rasterize returns, whichever the backend. The first three are the images; the rest are per input Gaussian.

    features (H, W, C) = sum w_i f_i; alpha (H, W) = sum w_i; depth (H, W) = sum w_i z_i / alpha (0 where
    alpha == 0), all in the inputs' dtype/device;
    means2d (M, 2) the 2D means in pixels ((1, M, 2) from the gsplat backend, its batched tensor): after
    backward, `means2d.grad` is the screen-space positional gradient in pixels (3DGS measures it in NDC:
    multiply by (W/2, H/2) to compare with its thresholds);
    radii (M,) int64 footprint radius in pixels, 0 for Gaussians that are culled or touch no pixel;
    visible (M,) bool, radii > 0.
    """

    features: Tensor
    alpha: Tensor
    depth: Tensor
    means2d: Tensor
    radii: Tensor
    visible: Tensor


def expected_depth(depth_sum: Tensor, alpha: Tensor) -> Tensor:
    """depth = sum w z / alpha where alpha > 0, else 0 (differentiable, no division by 0)."""
    covered = alpha > 0
    return torch.where(covered, depth_sum / torch.where(covered, alpha, torch.ones_like(alpha)),
                       torch.zeros_like(alpha))
