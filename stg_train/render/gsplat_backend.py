"""The `gsplat` backend: gsplat's CUDA `rasterization()` behind stg_train.render.rasterize.

Only the rasterisation moves to gsplat; the STG parts (time evaluation of positions, rotations,
opacities and features) stay in our torch code before the call. gsplat's "classic" mode uses the
constants of formats/stg-v1.md, section 3 (near plane 0.01, blur 0.3, 1.3x Jacobian clamp, 1/255,
0.99, 1e-4), so its images match the torch splatter's up to the decisions the spec lets fall either
way; its footprint radius is opacity-aware (smaller than 3 sigma where the opacity is low), which only
drops contributions below 1/255.

Install with the `[cuda]` extra (`pip install -e ".[cuda]"`); gsplat compiles its kernels on first use
and needs a CUDA device.
"""
from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from stg_runtime.spec import BLUR, NEAR

from .output import RenderOutput


def unavailable_reason(device) -> str | None:
    """None when gsplat can rasterise on `device` (a torch device or name), else why not."""
    try:
        import gsplat  # noqa: F401
    except ImportError:
        return "the gsplat package is not installed (pip install -e \".[cuda]\")"
    if torch.device(device).type != "cuda":
        return "gsplat needs --device cuda"
    if not torch.cuda.is_available():
        return "torch sees no CUDA device"
    return None


def camera_tensors(camera, device, dtype) -> tuple[Tensor, Tensor]:
    """gsplat's camera arguments for one stg_runtime Camera: viewmats (1, 4, 4) world-to-camera (OpenCV
    axes, as ours) and Ks (1, 3, 3) pinhole intrinsics in pixels (pixel centres at +0.5, as ours)."""
    viewmat = torch.tensor(np.array(camera.world_to_camera), dtype=dtype, device=device)[None]
    K = torch.tensor(np.array(camera.K), dtype=dtype, device=device)[None]
    return viewmat, K


def rasterize_gsplat(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, features: Tensor,
                     camera, *, rasterization=None) -> RenderOutput:
    """stg_train.render.rasterize through gsplat: same inputs, same RenderOutput.

    means (M, 3), quats (M, 4) wxyz, scales (M, 3), opacities (M,) or (M, 1), features (M, C) on a CUDA
    device; camera a stg_runtime Camera. `rasterization` replaces gsplat.rasterization (tests).
    `means2d.grad` after backward is in pixels, as the torch backend's.
    """
    if rasterization is None:
        from gsplat import rasterization
    viewmats, Ks = camera_tensors(camera, means.device, means.dtype)
    opacities = opacities.reshape(-1)
    colors, alphas, meta = rasterization(
        means, quats, scales, opacities, features.reshape(opacities.shape[0], -1), viewmats, Ks,
        camera.width, camera.height, near_plane=NEAR, eps2d=BLUR, packed=False,
        render_mode="RGB+ED", rasterize_mode="classic")
    means2d = meta["means2d"]  # (1, M, 2) pixels, a non-leaf of the graph: keep its gradient
    if means2d.requires_grad:
        means2d.retain_grad()
    radii = meta["radii"][0]
    if radii.dim() == 2:  # gsplat >= 1.5 gives per-axis radii
        visible = (radii > 0).all(-1)
        radii = radii.amax(-1)
    else:
        visible = radii > 0
    radii = torch.where(visible, radii, torch.zeros_like(radii)).to(torch.int64)
    alpha = alphas[0, ..., 0]
    depth = torch.where(alpha > 0, colors[0, ..., -1], torch.zeros_like(alpha))
    return RenderOutput(colors[0, ..., :-1], alpha, depth, means2d, radii, visible)
