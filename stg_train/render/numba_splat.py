"""The CPU training splatter: numba kernels with a backward pass, as two torch autograd functions.

    rasterize_numba(means, quats, scales, opacities, features, camera) -> RenderOutput

Same rules (formats/stg-v1.md, section 3) and same outputs as the torch splatter
(stg_train.render.torch_splat), value for value. `Project` is the EWA projection
(stg_train.render.numba_projection for pinholes, stg_train.render.numba_fisheye for fisheyes);
`Composite` the tiles and compositing (stg_train.render.numba_kernels): its forward pass composites
tile by tile and keeps two numbers per pixel, its backward pass walks each tile's list back to front.
Memory is proportional to Gaussians plus pixels, never to their product. The depth order and the tile
lists come from the runtime's splatter (stg_runtime.splat_cpu), so the forward pass draws what the
Player draws. CPU tensors only.
"""
from __future__ import annotations

import numba
import numpy as np
import torch
from torch import Tensor

from stg_runtime.projection import camera_params
from stg_runtime.splat_cpu import bin_tiles, sort_by_depth

from . import numba_kernels as kernels
from . import numba_fisheye, numba_projection
from .output import RenderOutput, expected_depth


class _Tiles:
    """What the backward pass needs from the forward pass, beside the inputs (numpy arrays)."""

    def __init__(self, rects, tile_start, tile_ids, tile_order, tiles_x, t_final, n_last):
        self.rects, self.tile_start, self.tile_ids, self.tile_order = rects, tile_start, tile_ids, tile_order
        self.tiles_x, self.t_final, self.n_last = tiles_x, t_final, n_last


def _numpy(t: Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.detach().numpy())


class Project(torch.autograd.Function):
    """EWA projection (pinhole or fisheye): (means (M, 3), quats (M, 4), scales (M, 3), opacities (M,),
    camera) -> (means2d (M, 2), conic (M, 3), depth (M,), radius (M,) int64, valid (M,) bool),
    differentiable in means, quats and scales (radius and valid are not; the opacities only decide
    validity)."""

    @staticmethod
    def forward(ctx, means, quats, scales, opacities, camera):
        arrays = [_numpy(x) for x in (means, quats, scales, opacities)]
        m, dtype = means.shape[0], means.dtype
        means2d, conic = torch.empty(m, 2, dtype=dtype), torch.empty(m, 3, dtype=dtype)
        depth = torch.empty(m, dtype=dtype)
        radius, valid = torch.empty(m, dtype=torch.int64), torch.empty(m, dtype=torch.bool)
        cam = camera_params(camera)
        kernels = numba_fisheye if camera.model == "fisheye" else numba_projection
        kernels.forward(*arrays, cam, means2d.numpy(), conic.numpy(), depth.numpy(), radius.numpy(), valid.numpy())
        ctx.arrays, ctx.cam, ctx.valid, ctx.kernels = arrays[:3], cam, valid.numpy(), kernels
        ctx.mark_non_differentiable(radius, valid)
        return means2d, conic, depth, radius, valid

    @staticmethod
    def backward(ctx, g_means2d, g_conic, g_depth, _g_radius, _g_valid):
        means, quats, scales = ctx.arrays
        grads = [np.zeros_like(x) for x in (means, quats, scales)]
        incoming = [np.zeros((means.shape[0],) + shape, means.dtype) if g is None else _numpy(g)
                    for g, shape in ((g_means2d, (2,)), (g_conic, (3,)), (g_depth, ()))]
        ctx.kernels.backward(means, quats, scales, ctx.cam, ctx.valid, *incoming, *grads)
        return (*[torch.from_numpy(g) for g in grads], None, None)


class Composite(torch.autograd.Function):
    """Composite projected Gaussians: (means2d (M, 2), conic (M, 3), opacity (M,), features (M, C),
    depth (M,)) -> (features (H, W, C), alpha (H, W), sum w z (H, W), visible (M,) bool), differentiable
    in all five inputs. radius (M,) int64 and valid (M,) bool come from the projection and carry no
    gradient; visible: valid and the 3-sigma footprint holds a pixel of the image."""

    @staticmethod
    def forward(ctx, means2d, conic, opacity, features, depth, radius, valid, width, height):
        arrays = [_numpy(x) for x in (means2d, conic, opacity, features, depth)]
        m2d, con, opa, feat, dep = arrays
        rects, tiles, visible = kernels.rectangles(m2d, con, opa, radius.numpy(), valid.numpy(), width, height)
        order = sort_by_depth(tiles, dep.astype(np.float64))
        tiles_x, tiles_y = -(-width // kernels.TILE), -(-height // kernels.TILE)
        padded = (tiles_y * kernels.TILE, tiles_x * kernels.TILE)  # the kernels work on whole tiles
        tile_start, tile_ids, tile_order = bin_tiles(order, tiles, tiles_x, tiles_y)
        out = np.zeros((feat.shape[1] + 2, *padded), feat.dtype)
        trans = np.ones(padded, feat.dtype)
        n_last = np.zeros(padded, np.int32)
        with numba.parallel_chunksize(1):
            kernels.forward(m2d, con, opa, feat, dep, rects, tile_start, tile_ids, tile_order, tiles_x,
                            kernels.constants(feat.dtype), out, trans, n_last)
        ctx.arrays = arrays
        ctx.tiles = _Tiles(rects, tile_start, tile_ids, tile_order, tiles_x, np.abs(trans), n_last)
        ctx.size = (height, width)
        visible = torch.from_numpy(visible)
        ctx.mark_non_differentiable(visible)
        out = torch.from_numpy(out)
        out = out[:, :height, :width]
        return out[:-2].permute(1, 2, 0), out[-2], out[-1], visible

    @staticmethod
    def backward(ctx, grad_features, grad_alpha, grad_depth_sum, _grad_visible):
        m2d, con, opa, feat, dep = ctx.arrays
        tl = ctx.tiles
        height, width = ctx.size
        channels = feat.shape[1]
        grad_out = np.zeros((channels + 2, *tl.t_final.shape), feat.dtype)
        if grad_features is not None:
            grad_out[:channels, :height, :width] = grad_features.detach().permute(2, 0, 1).numpy()
        for k, g in ((channels, grad_alpha), (channels + 1, grad_depth_sum)):
            if g is not None:
                grad_out[k, :height, :width] = g.detach().numpy()
        entry_grads = np.empty((tl.tile_ids.shape[0], kernels.GRAD_FEATURES + channels), feat.dtype)
        with numba.parallel_chunksize(1):
            kernels.backward(m2d, con, opa, feat, dep, tl.rects, tl.tile_start, tl.tile_ids, tl.tile_order,
                             tl.tiles_x, kernels.constants(feat.dtype), tl.t_final.copy(), tl.n_last, grad_out,
                             entry_grads)
        grads = np.zeros((m2d.shape[0], kernels.GRAD_FEATURES + channels), feat.dtype)
        kernels.sum_entries(tl.tile_ids, entry_grads, grads)
        total = torch.from_numpy(grads)
        return (total[:, 0:2], total[:, 2:5], total[:, kernels.GRAD_OPACITY], total[:, kernels.GRAD_FEATURES:],
                total[:, kernels.GRAD_DEPTH], None, None, None, None)


def rasterize_numba(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, features: Tensor,
                    camera) -> RenderOutput:
    """Render M Gaussians with the rules of formats/stg-v1.md, section 3, differentiably, on the CPU.

    means (M, 3) world positions; quats (M, 4) wxyz (normalised here); scales (M, 3) standard deviations
    (world units); opacities (M,) or (M, 1) in [0, 1]; features (M, C); camera: a
    stg_runtime.camera.Camera, pinhole or fisheye (fixed, no gradient). CPU tensors of one float dtype
    (float32 to train, float64 for gradient checks). Returns a RenderOutput like the torch splatter's."""
    if means.device.type != "cpu":
        raise ValueError(f"the numba splatter runs on the CPU; got tensors on {means.device}")
    W, H = camera.width, camera.height
    opacities = opacities.reshape(-1)
    features = features.reshape(opacities.shape[0], features.shape[-1])
    means2d, conic, z, radius, valid = Project.apply(means, quats, scales, opacities, camera)
    if means2d.requires_grad:
        means2d.retain_grad()
    feats, alpha, depth_sum, visible = Composite.apply(means2d, conic, opacities, features, z, radius, valid, W, H)
    radii = torch.where(visible, radius, torch.zeros_like(radius))
    depth = expected_depth(depth_sum, alpha)
    return RenderOutput(feats, alpha, depth, means2d, radii, visible)
