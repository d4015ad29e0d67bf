"""The `gsplat` backend: gsplat's CUDA `rasterization()` behind stg_train.render.rasterize.

Only the rasterisation moves to gsplat; the STG parts (time evaluation of positions, rotations,
opacities and features) stay in our torch code before the call. gsplat's "classic" mode uses the
constants of formats/stg-v1.md, section 3 (near plane 0.01, blur 0.3, 1.3x Jacobian clamp, 1/255,
0.99, 1e-4), so its images match the torch splatter's up to the decisions the spec lets fall either
way; its footprint radius is opacity-aware (smaller than 3 sigma where the opacity is low), which only
drops contributions below 1/255.

Fisheye cameras (spec section 3, "fisheye Jacobian"). gsplat has two fisheye paths (read in its
sources, versions 1.4 to 1.5.3 and its main branch):
- its EWA projection (`camera_model="fisheye"`, `with_ut=False`) is the equidistant fisheye only,
  theta_d = theta, with no k1..k4 (it refuses `radial_coeffs` without `with_ut`): the mean
  (fx x theta / r + cx, fy y theta / r + cy) and the covariance through that map's exact Jacobian,
  unclamped, culling z < near, which is our rule for k1 = k2 = k3 = k4 = 0 (it adds 1e-7 to r and to
  x^2 against division by zero: a relative change of about 1e-7 near the axis, below float32 noise);
- its unscented-transform path (`with_ut=True`, `radial_coeffs` (C, 4): OpenCV's fisheye with k1..k4,
  our camera model) replaces the Jacobian by sigma points pushed through the distortion, a different
  2D covariance than our spec's, and its projection is not differentiable (gsplat trains it with
  `with_eval3d=True`, evaluating each Gaussian in 3D along the pixel rays: a different renderer).
So an equidistant fisheye (all distortion coefficients zero) goes to gsplat's EWA path, and a fisheye
with any k_i != 0 falls back to our torch splatter (same device, same RenderOutput): what is trained is
then what the Player draws, at the torch splatter's speed.

Install with the `[cuda]` extra (`pip install -e ".[cuda]"`); gsplat compiles its kernels on first use
and needs a CUDA device.
"""
from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from stg_runtime.spec import BLUR, NEAR

from .output import RenderOutput
from .torch_splat import rasterize_torch


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


def covers(camera) -> bool:
    """Whether gsplat's EWA projection draws `camera` by our spec: a pinhole, or an equidistant fisheye
    (every distortion coefficient zero); see the module docstring."""
    return camera.model == "pinhole" or (camera.model == "fisheye" and not any(camera.distortion))


def camera_tensors(camera, device, dtype) -> tuple[Tensor, Tensor]:
    """gsplat's camera arguments for one stg_runtime Camera: viewmats (1, 4, 4) world-to-camera (OpenCV
    axes, as ours) and Ks (1, 3, 3) intrinsics in pixels (pixel centres at +0.5, as ours; the same
    matrix for gsplat's pinhole and fisheye models)."""
    viewmat = torch.tensor(np.array(camera.world_to_camera), dtype=dtype, device=device)[None]
    K = torch.tensor(np.array(camera.K), dtype=dtype, device=device)[None]
    return viewmat, K


def rasterize_gsplat(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, features: Tensor,
                     camera, *, rasterization=None) -> RenderOutput:
    """stg_train.render.rasterize through gsplat: same inputs, same RenderOutput.

    means (M, 3), quats (M, 4) wxyz, scales (M, 3), opacities (M,) or (M, 1), features (M, C) on a CUDA
    device; camera a stg_runtime Camera. `rasterization` replaces gsplat.rasterization (tests).
    `means2d.grad` after backward is in pixels, as the torch backend's. A camera that gsplat does not
    cover (`covers`: a fisheye with k1..k4 not all zero) is drawn by the torch splatter instead (its
    means2d is then (M, 2)).
    """
    if not covers(camera):
        return rasterize_torch(means, quats, scales, opacities, features, camera)
    if rasterization is None:
        from gsplat import rasterization
    viewmats, Ks = camera_tensors(camera, means.device, means.dtype)
    opacities = opacities.reshape(-1)
    colors, alphas, meta = rasterization(
        means, quats, scales, opacities, features.reshape(opacities.shape[0], -1), viewmats, Ks,
        camera.width, camera.height, near_plane=NEAR, eps2d=BLUR, packed=False,
        render_mode="RGB+ED", rasterize_mode="classic", camera_model=camera.model)
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
