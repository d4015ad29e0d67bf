"""Differentiable Gaussian splatting in plain torch (autograd): the trainer's renderer on any device.

The maths and constants are those of formats/stg-v1.md, section 3 (stg_runtime.spec), exactly as in
the float64 oracle stg_runtime.spec.rasterize_oracle and stg_runtime.splat_cpu (numba): EWA projection
with the near plane, Jacobian clamp, blur and determinant cull (a fisheye camera: the mean through the
distortion, the fisheye Jacobian unclamped, and the max_angle cull); 3-sigma radius; per-pixel footprint
test; front-to-back compositing in (depth, index) order with the 1/255 alpha floor, the 0.99 alpha cap
and the 1e-4 transmittance stop. Discrete decisions (culls, radii, order, thresholds, the stop) carry no
gradient; everything else is differentiable w.r.t. means, quats, scales, opacities and features.

How it is vectorised (no per-pixel Python loop):
  1. project all M Gaussians at once (`project`);
  2. bin them to `tile_size` x `tile_size` tiles with tensor ops: every (tile, Gaussian) pair whose
     footprint rectangle reaches a pixel centre of the tile, sorted by (tile, depth rank);
  3. walk the per-tile lists in chunks of `chunk` Gaussians, for a batch of tiles at a time: alpha for
     [tiles, pixels, chunk] at once (the quadratic form is separable over a tile's rows and columns);
     skipped contributions get alpha 0; log T before each Gaussian is log T_in plus an exclusive
     cumulative sum of log(1 - alpha) (a matmul with a triangular matrix: cumprod's backward is slow
     on CPU), carried across chunks. Skipped contributions leave T unchanged, so T is monotone and the
     stop rule is a mask: Gaussian k is added iff T after it (inclusive product) >= 1e-4 and the pixel
     had not stopped in an earlier chunk. Tiles whose pixels have all stopped, or whose lists are
     exhausted, drop out of later chunks.

Memory: every chunk's autograd intermediates (about five float and two bool tensors of tiles x pixels
x chunk) are kept for backward, so memory grows with the number of (tile, Gaussian) pairs actually
composited times tile_size^2; `checkpoint=True` with a smaller `max_elements` bounds it by one batch of
tiles, at more time. docs/performance.md has the measured time and memory.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import torch
import torch.utils.checkpoint
from torch import Tensor

from stg_runtime.spec import BLUR, JACOBIAN_MARGIN, MAX_ALPHA, MIN_ALPHA, NEAR, T_STOP

from .output import RenderOutput, expected_depth

LOG_T_STOP = math.log(T_STOP)


class Projection(NamedTuple):
    """Per-Gaussian screen-space footprint (M = number of input Gaussians).

    means2d (M, 2) pixels, the unclamped projection (u, v), differentiable (culled rows: finite junk);
    conic (M, 3) [A, B, C], the inverse of the blurred 2D covariance [[A, B], [B, C]] (0 if culled);
    depth (M,) camera-space z, differentiable; radius (M,) int64 pixels (0 if culled);
    valid (M,) bool: in front of the near plane, determinant > 0 and opacity >= 1/255.
    """

    means2d: Tensor
    conic: Tensor
    depth: Tensor
    radius: Tensor
    valid: Tensor


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """(M, 4) wxyz quaternions, any non-zero length (normalised here) -> (M, 3, 3) rotation matrices."""
    q = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-30)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).reshape(-1, 3, 3)


def project(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, camera) -> Projection:
    """EWA projection of M Gaussians (means (M, 3) world, quats (M, 4) wxyz, scales (M, 3) standard
    deviations in world units, opacities (M,)) through `camera` (stg_runtime.camera.Camera, pinhole or
    fisheye)."""
    dev, dt = means.device, means.dtype
    Rc = torch.tensor(camera.R, dtype=dt, device=dev)
    tc = torch.tensor(camera.t, dtype=dt, device=dev)

    p = means @ Rc.T + tc
    if camera.model == "fisheye":
        in_front, means2d, J = _fisheye(p, camera)
    else:
        in_front, means2d, J = _pinhole(p, camera)

    # Sigma = R S S^T R^T in camera space, through J: cov2d = T T^T with T = J R_cam R S.
    RS = quat_to_rotmat(quats) * scales[:, None, :]
    T = (J @ Rc) @ RS  # (M, 2, 3)
    cov = T @ T.transpose(1, 2)
    a = cov[:, 0, 0] + BLUR
    b = cov[:, 0, 1]
    c = cov[:, 1, 1] + BLUR
    det = a * c - b * b
    valid = in_front & (det > 0) & (opacities.detach().reshape(-1) >= MIN_ALPHA)
    dets = torch.where(valid, det, torch.ones_like(det))
    conic = torch.stack([c / dets, -b / dets, a / dets], dim=-1) * valid[:, None]
    with torch.no_grad():
        m = 0.5 * (a + c)
        lam = m + torch.sqrt(torch.clamp(m * m - det, min=0.1))
        radius = torch.where(valid, torch.ceil(3.0 * torch.sqrt(lam.clamp_min(0))), torch.zeros_like(lam))
    return Projection(means2d, conic, p[:, 2], radius.to(torch.int64), valid)


def _pinhole(p: Tensor, camera) -> tuple[Tensor, Tensor, Tensor]:
    """Camera-space points p (M, 3) -> (in front of the near plane (M,) bool, the 2D means (M, 2) pixels,
    the EWA Jacobians (M, 2, 3) with x/z, y/z clamped to 1.3 x the half field of view). Culled rows:
    z taken as 1 (finite values and gradients)."""
    W, H = camera.width, camera.height
    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
    x, y, z = p.unbind(-1)
    in_front = z > NEAR
    zs = torch.where(in_front, z, torch.ones_like(z))  # no division by ~0 for culled rows (keeps grads finite)
    means2d = torch.stack([fx * x / zs + cx, fy * y / zs + cy], dim=-1)
    tan_x, tan_y = W / (2 * fx), H / (2 * fy)
    xz = (x / zs).clamp(-(cx / fx + JACOBIAN_MARGIN * tan_x), (W - cx) / fx + JACOBIAN_MARGIN * tan_x)
    yz = (y / zs).clamp(-(cy / fy + JACOBIAN_MARGIN * tan_y), (H - cy) / fy + JACOBIAN_MARGIN * tan_y)
    zero = torch.zeros_like(zs)
    J = torch.stack([fx / zs, zero, -fx * xz / zs, zero, fy / zs, -fy * yz / zs], -1).reshape(-1, 2, 3)
    return in_front, means2d, J


def _fisheye(p: Tensor, camera) -> tuple[Tensor, Tensor, Tensor]:
    """Camera-space points p (M, 3) -> (seen (M,) bool: z > NEAR and theta < camera.max_angle, the 2D
    means (M, 2) pixels, the fisheye Jacobians (M, 2, 3) at the unclamped means; formats/stg-v1.md
    sections 1 and 3, as stg_runtime.spec.fisheye_jacobian). theta = atan2(r, z), r = |(x, y)|; on the
    axis (r <= 1e-7 z) the limits (theta taken as 0). Culled rows are replaced by the point (0, 0, 1):
    their means are (cx, cy) and every value and gradient stays finite (no sqrt or atan2 at 0)."""
    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
    k1, k2, k3, k4 = camera.distortion
    with torch.no_grad():
        x, y, z = p.unbind(-1)
        seen = (z > NEAR) & (torch.atan2(torch.sqrt(x * x + y * y), z) < camera.max_angle)
    p = torch.where(seen[:, None], p, torch.tensor([0.0, 0.0, 1.0], dtype=p.dtype, device=p.device))
    x, y, z = p.unbind(-1)
    r2 = x * x + y * y
    off_axis = r2 > (1e-7 * z) ** 2  # r > 1e-7 z, as z > 0 here
    r2s = torch.where(off_axis, r2, torch.ones_like(r2))
    r = torch.sqrt(r2s)
    theta = torch.where(off_axis, torch.atan2(r, z), torch.zeros_like(z))
    t2 = theta * theta
    theta_d = theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
    slope = 1 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))  # d theta_d / d theta
    rho2 = r2 + z * z
    radial = torch.where(off_axis, theta_d / r, 1 / z)  # theta_d / r
    ar = torch.where(off_axis, (slope * z / rho2 - theta_d / r) / r2s, (2 * k1 - 2 / 3) / z ** 3)  # radial'(r) / r
    means2d = torch.stack([fx * x * radial + cx, fy * y * radial + cy], dim=-1)
    J = torch.stack([fx * (radial + x * x * ar), fx * x * y * ar, -fx * x * slope / rho2,
                     fy * x * y * ar, fy * (radial + y * y * ar), -fy * y * slope / rho2], -1).reshape(-1, 2, 3)
    return seen, means2d, J


def _bin(mu: Tensor, radius: Tensor, depth: Tensor, valid: Tensor, W: int, H: int, ts: int):
    """(tile, Gaussian) pairs sorted by tile then (depth, index). No gradient.

    Returns (gauss (P,) int64 Gaussian of each pair, tile_start (nt,), tile_count (nt,), radii (M,)
    with 0 for Gaussians that reach no pixel centre, visible (M,))."""
    M, dev = mu.shape[0], mu.device
    ntx, nty = -(-W // ts), -(-H // ts)
    r = radius.to(mu.dtype)
    # Pixel columns u with |u + 0.5 - mu_x| <= r, rows likewise, clipped to the image.
    c0 = torch.ceil(mu[:, 0] - r - 0.5).clamp(min=0)
    c1 = torch.floor(mu[:, 0] + r - 0.5).clamp(max=W - 1)
    r0 = torch.ceil(mu[:, 1] - r - 0.5).clamp(min=0)
    r1 = torch.floor(mu[:, 1] + r - 0.5).clamp(max=H - 1)
    visible = valid & (c0 <= c1) & (r0 <= r1)
    radii = torch.where(visible, radius, torch.zeros_like(radius))
    idx = torch.nonzero(visible).squeeze(1)
    tx0 = (c0[idx] // ts).long()
    ty0 = (r0[idx] // ts).long()
    nx = (c1[idx] // ts).long() - tx0 + 1
    ny = (r1[idx] // ts).long() - ty0 + 1
    counts = nx * ny
    total = int(counts.sum())
    pair_g = torch.repeat_interleave(torch.arange(idx.shape[0], device=dev), counts, output_size=total)
    k = torch.arange(total, device=dev) - (torch.cumsum(counts, 0) - counts)[pair_g]
    tile = (ty0[pair_g] + k // nx[pair_g]) * ntx + tx0[pair_g] + k % nx[pair_g]
    # Depth rank over all Gaussians (stable sort: ties by index), then sort pairs by (tile, rank).
    order = torch.sort(torch.where(visible, depth, torch.full_like(depth, float("inf"))), stable=True).indices
    rank = torch.empty_like(order)
    rank[order] = torch.arange(M, device=dev)
    gauss = idx[pair_g]
    key = tile * M + rank[gauss]
    gauss = gauss[torch.sort(key).indices]
    tile_count = torch.bincount(tile, minlength=ntx * nty)
    tile_start = torch.cumsum(tile_count, 0) - tile_count
    return gauss, tile_start, tile_count, radii, visible


def _composite_batch(tiles: Tensor, start: Tensor, count: Tensor, gauss: Tensor, per_g: Tensor,
                     vals: Tensor, ntx: int, ts: int, chunk: int) -> Tensor:
    """Composite one batch of tiles (nb,). per_g (M+1, 7) = [mu_x, mu_y, A, B, C, log opacity, radius] with
    a dummy last row that touches nothing; vals (M+1, C+2) = [features, 1, z]. Returns (nb, ts*ts, C+2)
    sums of w * vals."""
    dev, dt = per_g.device, per_g.dtype
    nb, P, D = tiles.shape[0], ts * ts, vals.shape[1]
    dummy = per_g.shape[0] - 1
    lane = torch.arange(ts, device=dev, dtype=dt) + 0.5
    px = (tiles % ntx * ts).to(dt)[:, None] + lane  # (nb, ts) pixel-centre x of the tile's columns
    py = (tiles // ntx * ts).to(dt)[:, None] + lane  # (nb, ts) rows
    acc = torch.zeros(nb, P, D, dtype=dt, device=dev)
    logT = torch.zeros(nb, P, dtype=dt, device=dev)
    excl = torch.ones(chunk, chunk, dtype=dt, device=dev).triu_(1)  # excl[j, k] = 1 for j < k
    done = torch.zeros(nb, P, dtype=torch.bool, device=dev)
    offs = torch.arange(chunk, device=dev)
    longest = int(count.max()) if nb else 0
    for c0 in range(0, longest, chunk):
        act = torch.nonzero((count > c0) & ~done.all(1)).squeeze(1)
        if act.numel() == 0:
            break
        pos = c0 + offs
        in_list = pos[None, :] < count[act, None]
        g = torch.where(in_list, gauss[(start[act, None] + pos).clamp(max=gauss.shape[0] - 1)], dummy)
        q = per_g[g]  # (na, K, 7)
        mx, my, A, B, C, logo, r = q.unbind(-1)
        dx = px[act, :, None] - mx[:, None, :]  # (na, ts columns, K)
        dy = py[act, :, None] - my[:, None, :]  # (na, ts rows, K)
        # npow = log(opacity) - power over (na, rows, columns, K), separably, with
        # power = 0.5 (A dx^2 + C dy^2) + B dx dy; -inf outside the footprint |d| <= r (then alpha = 0).
        rr = r[:, None, :]
        X = torch.where(dx.abs() <= rr, logo[:, None, :] - 0.5 * A[:, None, :] * dx * dx, -math.inf)
        Y = torch.where(dy.abs() <= rr, -0.5 * C[:, None, :] * dy * dy, -math.inf)
        npow = (Y[:, :, None, :] + X[:, None, :, :]).addcmul_((-B[:, None, :] * dx)[:, None, :, :], dy[:, :, None, :])
        raw = torch.exp(npow)  # opacity * exp(-power)
        with torch.no_grad():  # skipped: power < 0, alpha < 1/255 (and outside the footprint)
            skip = (npow > logo[:, None, None, :]).logical_or_(raw < MIN_ALPHA)
        alpha = raw.clamp(max=MAX_ALPHA).masked_fill_(skip, 0.0).reshape(-1, P, chunk)
        # Transmittance in log space; the exclusive cumulative sum over the chunk is a matmul with a
        # strictly upper-triangular matrix of ones (much faster than cumprod's backward on CPU).
        la = torch.log1p(-alpha)  # log(1 - alpha), 0 where skipped
        logTin = logT[act]
        lex = torch.matmul(la, excl) + logTin[..., None]  # log T before each Gaussian
        with torch.no_grad():  # stopped: T (1 - alpha) < 1e-4 here or earlier
            dead = (lex + la < LOG_T_STOP).logical_or_(done[act][..., None])
        w = (alpha * torch.exp(lex)).masked_fill_(dead, 0.0)
        out = torch.bmm(w, vals[g])  # (na, P, C+2)
        acc = acc.index_add(0, act, out)
        # Carry log T (its value only matters for pixels that have not stopped).
        logT = logT.index_copy(0, act, logTin + la.sum(-1))
        done = done.index_copy(0, act, dead[..., -1])
    return acc


def rasterize_torch(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, features: Tensor, camera,
                    *, tile_size: int = 8, chunk: int = 32, max_elements: int = 1 << 22,
                    checkpoint: bool = False) -> RenderOutput:
    """Render M Gaussians with the rules of formats/stg-v1.md, section 3 (see module docstring).

    means (M, 3) world positions; quats (M, 4) wxyz (normalised here); scales (M, 3) standard deviations
    (world units); opacities (M,) or (M, 1) in [0, 1]; features (M, C); camera: a
    stg_runtime.camera.Camera (fixed, no gradient). All tensors on one device, one float dtype.
    tile_size, chunk, max_elements (tiles x pixels x chunk per batch) and checkpoint only change speed
    and memory, never the result; checkpoint=True recomputes each batch of tiles during backward
    instead of keeping its intermediates (memory bounded by one batch, at more time: docs/performance.md).
    Returns a RenderOutput (features, alpha, depth, means2d, radii, visible).
    """
    W, H = camera.width, camera.height
    ts = int(tile_size)
    ntx, nty = -(-W // ts), -(-H // ts)
    opacities = opacities.reshape(-1)
    features = features.reshape(opacities.shape[0], features.shape[-1])
    dev, dt = means.device, means.dtype
    proj = project(means, quats, scales, opacities, camera)
    means2d = proj.means2d
    if means2d.requires_grad:
        means2d.retain_grad()
    gauss, tile_start, tile_count, radii, visible = _bin(
        means2d.detach(), proj.radius, proj.depth.detach(), proj.valid, W, H, ts)

    # log(opacity) is finite for every Gaussian that can be in a tile list (opacity >= 1/255).
    logo = torch.log(torch.where(proj.valid, opacities, torch.ones_like(opacities)))
    per_g = torch.cat([means2d, proj.conic, logo[:, None], proj.radius[:, None].to(dt)], 1)
    per_g = torch.cat([per_g, torch.tensor([[0, 0, 0, 0, 0, 0, -1]], dtype=dt, device=dev)], 0)  # dummy row
    vals = torch.cat([features, torch.ones_like(opacities)[:, None], proj.depth[:, None]], 1)
    vals = torch.cat([vals, torch.zeros(1, vals.shape[1], dtype=dt, device=dev)], 0)

    # Batches of tiles with similar list lengths (longest first), at most max_elements per chunk step.
    ntiles, P = ntx * nty, ts * ts
    order = torch.sort(tile_count, descending=True, stable=True).indices
    order = order[tile_count[order] > 0]
    per_batch = max(1, max_elements // (P * chunk))
    parts, done_tiles = [], []
    for b0 in range(0, order.shape[0], per_batch):
        tiles = order[b0:b0 + per_batch]
        args = (tiles, tile_start[tiles], tile_count[tiles], gauss, per_g, vals, ntx, ts, chunk)
        if checkpoint and torch.is_grad_enabled():
            parts.append(torch.utils.checkpoint.checkpoint(_composite_batch, *args, use_reentrant=False))
        else:
            parts.append(_composite_batch(*args))
        done_tiles.append(tiles)
    D = vals.shape[1]
    img = torch.zeros(ntiles, P, D, dtype=dt, device=dev)
    if parts:
        img = img.index_copy(0, torch.cat(done_tiles), torch.cat(parts))
    else:  # nothing visible: keep the outputs attached to the graph so backward still works
        img = img + 0 * (per_g.sum() + vals.sum() + means.sum() + quats.sum() + scales.sum())
    img = img.reshape(nty, ntx, ts, ts, D).permute(0, 2, 1, 3, 4).reshape(nty * ts, ntx * ts, D)[:H, :W]
    feats, alpha, num = img[..., :-2], img[..., -2], img[..., -1]
    depth = expected_depth(num, alpha)
    return RenderOutput(feats, alpha, depth, means2d, radii, visible)
