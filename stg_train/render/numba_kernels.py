"""The numba kernels of the CPU training splatter (no torch here): tiles, compositing and its gradient.

    rectangles(means2d, conic, opacity, radius, valid, width, height) -> rects, tiles, visible
    forward(..., out, trans, n_last)         composite every tile front to back (formats/stg-v1.md, 3)
    backward(..., grad_out, entry_grads)     the vector-Jacobian product, back to front, per list entry
    sum_entries(tile_ids, entry_grads, grads) per Gaussian: the sum of its entries' gradients
    constants(dtype)                         the spec's constants as the kernels take them

The projection (stg_train.render.numba_projection) hands over per Gaussian i:
means2d (M, 2) pixels, conic (M, 3) [A, B, C] with power = 0.5 (A dx^2 + C dy^2) + B dx dy, opacity (M,),
depth (M,) camera-space z, radius (M,) the spec's 3-sigma footprint in pixels and valid (M,). Each
pixel composites, in (depth, index) order, the Gaussians whose footprint reaches its centre, with the
spec's rules (power < 0 and alpha < 1/255 skipped, alpha capped at 0.99, the pixel stops before a
contribution that would take T below 1e-4). The outputs per pixel are out = [sum w f_c (C channels),
sum w, sum w z], w = alpha T.

The forward pass keeps, per pixel, T_final and n_last (how many entries of its tile's list it went
through, up to its last added contribution). The backward pass walks each tile's list from there back
to the front, recovering T before each Gaussian as T_after / (1 - alpha) (3D Gaussian Splatting's
scheme), so nothing per (pixel, Gaussian) is stored. Per pixel and contribution i, with g the output
gradient and v_i = [f_i, 1, z_i]:

    dL/dalpha_i = T_i (g . v_i) - (sum_{k > i} w_k (g . v_k)) / (1 - alpha_i)
    dL/df_i = w_i g_f,  dL/dz_i = w_i g_z
    alpha_i = o_i exp(-power): dL/do_i = dL/dalpha_i exp(-power), dL/dpower = -alpha_i dL/dalpha_i
    (no gradient where the 0.99 cap applies), and power's derivatives in mean2d and the conic.

Per-Gaussian sums are race-free and reproducible: `backward` writes each tile-list entry's gradient
into its own row (every entry belongs to one tile, which one thread processes), and `sum_entries` adds
the rows up per Gaussian in list order, serially: the gradient is the same in every run, whatever the
number of threads.
Works in the inputs' float dtype (float32 for training, float64 for the gradient checks).
"""
from __future__ import annotations

import math

import numba
import numpy as np
from numba import types
from numba.extending import overload

from stg_runtime.splat_cpu import exp_neg as exp_neg32
from stg_runtime.spec import MAX_ALPHA, MAX_ALPHA32, MIN_ALPHA, MIN_ALPHA32, T_STOP, T_STOP32

#: Tile edge in pixels, a compile-time constant (the kernels' loops are over a tile's rows).
TILE = 16
#: Pixels in a tile: the length of each plane of a tile's state.
PLANE = TILE * TILE
#: A plane is stored in STRIPS strips of STRIP_WIDTH columns (8 float32 lanes of AVX2), each row-major
#: (STRIP pixels): a Gaussian's run in a strip is its rows there, STRIP_WIDTH pixels each, so a narrow
#: Gaussian costs half the lanes of whole tile rows.
STRIP_WIDTH = 8
STRIPS = TILE // STRIP_WIDTH
STRIP = TILE * STRIP_WIDTH
#: Columns of the per-Gaussian gradient rows that `backward` writes: d mean2d (x, y), d conic (A, B,
#: C), d opacity, d depth, then d features (C channels).
GRAD_MEANS2D, GRAD_CONIC, GRAD_OPACITY, GRAD_DEPTH, GRAD_FEATURES = 0, 2, 5, 6, 7


@numba.njit(cache=True)
def rectangles(means2d, conic, opacity, radius, valid, width, height):
    """Per Gaussian, the inclusive rectangle of pixels it can reach and the tiles that rectangle meets.

    The footprint is the pixel centres within the 3-sigma radius (|p - mu| <= radius per axis); the
    rectangle keeps those that are also inside the ellipse where alpha can reach 1/255 (power <=
    log(255 o), plus 0.01 for rounding), clipped to the image. Returns rects (M, 4) int32 [u0, u1, v0,
    v1], tiles (M, 4) int32 [tx0, tx1, ty0, ty1] of TILE-pixel tiles (both empty, first > second, when
    culled or when no pixel can be reached) and visible (M,) bool: valid and the footprint holds a pixel of the image
    (the torch splatter's `visible`)."""
    m = means2d.shape[0]
    rects = np.empty((m, 4), np.int32)
    tiles = np.empty((m, 4), np.int32)
    visible = np.zeros(m, np.bool_)
    for i in range(m):
        rects[i, 0], rects[i, 1], rects[i, 2], rects[i, 3] = 1, 0, 1, 0
        tiles[i, 0], tiles[i, 1], tiles[i, 2], tiles[i, 3] = 1, 0, 1, 0
        if not valid[i]:
            continue
        u, v = np.float64(means2d[i, 0]), np.float64(means2d[i, 1])
        r = np.float64(radius[i])
        u0, u1 = _pixel_range(u, r, width)
        v0, v1 = _pixel_range(v, r, height)
        if u0 > u1 or v0 > v1:
            continue
        visible[i] = True
        a, b, c = np.float64(conic[i, 0]), np.float64(conic[i, 1]), np.float64(conic[i, 2])
        det = a * c - b * b
        if not det > 0.0:
            continue
        thr = math.log(255.0 * np.float64(opacity[i])) + 0.01
        u0, u1 = _pixel_range(u, min(r, math.sqrt(max(2.0 * thr * c / det, 0.0))), width)  # (conic^-1)_xx = c / det
        v0, v1 = _pixel_range(v, min(r, math.sqrt(max(2.0 * thr * a / det, 0.0))), height)
        if u0 > u1 or v0 > v1:
            continue
        rects[i, 0], rects[i, 1], rects[i, 2], rects[i, 3] = u0, u1, v0, v1
        tiles[i, 0], tiles[i, 1] = u0 // TILE, u1 // TILE
        tiles[i, 2], tiles[i, 3] = v0 // TILE, v1 // TILE
    return rects, tiles, visible


@numba.njit(inline="always")
def _pixel_range(centre, half, size):
    """The pixels k in [0, size) whose centres k + 0.5 lie in [centre - half, centre + half]: (first,
    last), first > last when none (the bounds clamped to [-1, size] first, where integers are exact)."""
    lo = min(max(centre - half - 0.5, -1.0), np.float64(size))
    hi = min(max(centre + half - 0.5, -1.0), np.float64(size))
    return max(int(math.ceil(lo)), 0), min(int(math.floor(hi)), size - 1)


def constants(dtype) -> np.ndarray:
    """The spec's constants in the working dtype, as the kernels take them (`consts`): 0.5, 1, 0, the
    alpha cap, the alpha floor and the transmittance stop. Passing them as an array keeps float32
    kernels in float32 (a literal would promote every operation to float64)."""
    if np.dtype(dtype) == np.float32:
        return np.array([0.5, 1.0, 0.0, MAX_ALPHA32, MIN_ALPHA32, T_STOP32], np.float32)
    return np.array([0.5, 1.0, 0.0, MAX_ALPHA, MIN_ALPHA, T_STOP], dtype)


def exp_neg(p):
    """exp(-p): numba picks the implementation by type (see _exp_neg_impl)."""
    return math.exp(-p)


@overload(exp_neg, inline="always")
def _exp_neg_impl(p):
    """float32: the runtime splatter's branch-free polynomial (it vectorises; p <= 87 expected);
    float64: libm's exp (exact reference for the gradient checks)."""
    if p == types.float32:
        return lambda p: exp_neg32(p)
    return lambda p: math.exp(-p)


@numba.njit(inline="always")
def _tile_state(planes, x0, y0, dtype):
    """A tile's state: `planes` planes of PLANE pixels (in strips, see _pixel), zeros, except the
    planes CENTRE_X and CENTRE_Y, the pixel centres (x0 + column + 0.5, y0 + row + 0.5), held in the
    working dtype (computing them in the loops would mix integers in, and numba promotes int64 with
    float32 to float64), and a spare scalar slot at the end."""
    S = np.zeros(planes * PLANE + 1, dtype)
    for r in range(TILE):
        for l in range(TILE):
            S[CENTRE_X * PLANE + _pixel(r, l)] = x0 + l + 0.5
            S[CENTRE_Y * PLANE + _pixel(r, l)] = y0 + r + 0.5
    return S


@numba.njit(inline="always")
def _pixel(r, l):
    """The index in a plane of the tile's pixel at row r, column l (strip by strip, row-major in each)."""
    return (l // STRIP_WIDTH) * STRIP + r * STRIP_WIDTH + l % STRIP_WIDTH


@numba.njit(inline="always")
def _run(rects, g, x0, y0, strip):
    """(start, length) of Gaussian g's run in the tile at (x0, y0): the rows of its rectangle in `strip`,
    whole strip rows (its columns are masked by the pixel centres); length 0 when it misses the strip."""
    c0 = x0 + strip * STRIP_WIDTH
    if rects[g, 1] < c0 or rects[g, 0] > c0 + STRIP_WIDTH - 1:
        return 0, 0
    top = max(rects[g, 2], y0) - y0
    return strip * STRIP + top * STRIP_WIDTH, (min(rects[g, 3], y0 + TILE - 1) - y0 - top + 1) * STRIP_WIDTH


@numba.njit(inline="always")
def _as_dtype(S, value):
    """value (an integer) in the dtype of S, through its spare slot."""
    S[S.shape[0] - 1] = value
    return S[S.shape[0] - 1]


@numba.njit(inline="always")
def _padded_channels(channels):
    """The feature planes of a tile's state: channels rounded up to a multiple of 3, at least 3 (the
    kernels take channels three at a time; the padding planes stay zero)."""
    return max(3, -(-channels // 3) * 3)


@numba.njit(inline="always")
def _feature(features, g, ch, zero):
    """features[g, ch], or zero for a padding channel (ch >= C)."""
    return features[g, ch] if ch < features.shape[1] else zero


@numba.njit(inline="always")
def _set_feature(E, ch, value, channels):
    """E[GRAD_FEATURES + ch] = value, for a real channel (ch < channels)."""
    if ch < channels:
        E[GRAD_FEATURES + ch] = value


#: Planes of a tile's state shared by both kernels: the pixel centres.
CENTRE_X, CENTRE_Y = 0, 1
#: The forward kernel's other planes: transmittance, entry count, the current weights, sum w, sum w z,
#: then sum w f per channel.
F_T, F_COUNT, F_WEIGHT, F_ALPHA, F_DEPTH, F_FEATURES = 2, 3, 4, 5, 6, 7
#: The backward kernel's other planes: transmittance, entry count, the suffix sum of w (g . v), g . v,
#: the current weights, dL/d alpha, dL/d depth sum, then dL/d features per channel.
B_T, B_COUNT, B_SUFFIX, B_GV, B_WEIGHT, B_GALPHA, B_GDEPTH, B_GFEATURES = 2, 3, 4, 5, 6, 7, 8, 9


@numba.njit(parallel=True, cache=True, fastmath={"contract"})
def forward(means2d, conic, opacity, features, depth, rects, tile_start, tile_ids, tile_order, tiles_x, consts,
            out, trans, n_last):
    """Composite every tile (lists as made by stg_runtime.splat_cpu.bin_tiles: tile t lists the Gaussian
    ids tile_ids[tile_start[t]:tile_start[t + 1]] front to back; tile_order is the work order).

    Writes out (C + 2, H, W): the planes [sum w f_c, sum w, sum w z]; trans (H, W): the final
    transmittance, negated where the pixel stopped; n_last (H, W) int32: how many list entries the
    pixel went through up to its last added contribution. H and W are padded to whole tiles.

    A tile's state is one array of planes (F_*). Per Gaussian and strip, the rows of its rectangle are
    one run of pixels (_run), composited by one branch-free loop (pixels outside the rectangle masked)
    that reads and writes the planes at constant offsets, which LLVM vectorises without aliasing
    checks, the first three feature channels with it; then one loop per three further channels."""
    half, one, zero, max_alpha, min_alpha, t_stop = consts[0], consts[1], consts[2], consts[3], consts[4], consts[5]
    channels = features.shape[1]
    c3 = _padded_channels(channels)
    for i in numba.prange(tile_order.shape[0]):
        tile = tile_order[i]
        x0 = (tile % tiles_x) * TILE
        y0 = (tile // tiles_x) * TILE
        S = _tile_state(F_FEATURES + c3, x0, y0, out.dtype)
        S[F_T * PLANE:(F_T + 1) * PLANE] = one
        n_live = PLANE
        start = tile_start[tile]
        for k in range(start, tile_start[tile + 1]):
            g = tile_ids[k]
            mx, my, a, b, c = means2d[g, 0], means2d[g, 1], conic[g, 0], conic[g, 1], conic[g, 2]
            o, z = opacity[g], depth[g]
            f0, f1, f2 = _feature(features, g, 0, zero), _feature(features, g, 1, zero), _feature(features, g, 2, zero)
            # the rectangle's first and last columns
            left = S[CENTRE_X * PLANE + _pixel(0, max(rects[g, 0] - x0, 0))]
            right = S[CENTRE_X * PLANE + _pixel(0, min(rects[g, 1] - x0, TILE - 1))]
            count = _as_dtype(S, k - start + 1)
            for strip in range(STRIPS):
                lo, n = _run(rects, g, x0, y0, strip)
                V = S[lo:]
                stops = 0
                for l in range(n):
                    px = V[l + CENTRE_X * PLANE]
                    dx = px - mx
                    dy = V[l + CENTRE_Y * PLANE] - my
                    power = half * (a * dx * dx + c * dy * dy) + b * dx * dy
                    alpha = min(max_alpha, o * exp_neg(power))
                    t = V[l + F_T * PLANE]
                    ok = (px >= left) & (px <= right) & (t > zero) & (power >= zero) & (alpha >= min_alpha)
                    t_next = t * (one - alpha)
                    stop = ok & (t_next < t_stop)
                    add = ok & (t_next >= t_stop)
                    w = alpha * t if add else zero
                    V[l + F_T * PLANE] = t_next if add else (-t if stop else t)
                    V[l + F_COUNT * PLANE] = count if add else V[l + F_COUNT * PLANE]
                    V[l + F_WEIGHT * PLANE] = w
                    V[l + F_ALPHA * PLANE] += w
                    V[l + F_DEPTH * PLANE] += w * z
                    V[l + F_FEATURES * PLANE] += w * f0
                    V[l + (F_FEATURES + 1) * PLANE] += w * f1
                    V[l + (F_FEATURES + 2) * PLANE] += w * f2
                    stops += stop
                n_live -= stops
                for ch in range(3, c3, 3):  # further channels, three at a time
                    fa, fb, fc = _feature(features, g, ch, zero), _feature(features, g, ch + 1, zero), \
                        _feature(features, g, ch + 2, zero)
                    F = V[(F_FEATURES + ch) * PLANE:]
                    for l in range(n):
                        w = V[l + F_WEIGHT * PLANE]
                        F[l] += w * fa
                        F[l + PLANE] += w * fb
                        F[l + 2 * PLANE] += w * fc
            if n_live == 0:
                break
        for r in range(TILE):
            y = y0 + r
            for l in range(TILE):
                p = _pixel(r, l)
                trans[y, x0 + l] = S[F_T * PLANE + p]
                n_last[y, x0 + l] = np.int32(S[F_COUNT * PLANE + p])
                out[channels, y, x0 + l] = S[F_ALPHA * PLANE + p]
                out[channels + 1, y, x0 + l] = S[F_DEPTH * PLANE + p]
            for ch in range(channels):
                for l in range(TILE):
                    out[ch, y, x0 + l] = S[(F_FEATURES + ch) * PLANE + _pixel(r, l)]


@numba.njit(parallel=True, cache=True, fastmath={"contract", "reassoc", "nsz"})
def backward(means2d, conic, opacity, features, depth, rects, tile_start, tile_ids, tile_order, tiles_x, consts,
             trans, n_last, grad_out, entry_grads):
    """The gradient of every tile-list entry's contributions: entry_grads (entries, 7 + C) (columns
    GRAD_*), row k for the Gaussian tile_ids[k] in its tile (zero where no pixel of the tile reached
    it). Tiles are taken in tile_order, in parallel. sum_entries adds the rows up per Gaussian.

    trans (H, W): the forward pass's final transmittance, made non-negative; n_last (H, W) from the
    forward pass; grad_out (C + 2, H, W): dL/d out, planes as forward's `out`; all padded to whole
    tiles. A tile's state is one array of planes (B_*), walked as in `forward`: per Gaussian and strip,
    g . v over its run of pixels less the first three feature channels, then one branch-free loop
    (vectorised, its sums reassociated, those three channels' sums with it); then one sum per three
    further channels over its runs."""
    half, one, zero, max_alpha, min_alpha = consts[0], consts[1], consts[2], consts[3], consts[4]
    channels = features.shape[1]
    c3 = _padded_channels(channels)
    for i in numba.prange(tile_order.shape[0]):
        tile = tile_order[i]
        x0 = (tile % tiles_x) * TILE
        y0 = (tile // tiles_x) * TILE
        S = _tile_state(B_GFEATURES + c3, x0, y0, entry_grads.dtype)
        deepest = 0
        for r in range(TILE):
            y = y0 + r
            for l in range(TILE):
                p = _pixel(r, l)
                S[B_T * PLANE + p] = trans[y, x0 + l]
                S[B_COUNT * PLANE + p] = n_last[y, x0 + l]
                S[B_GALPHA * PLANE + p] = grad_out[channels, y, x0 + l]
                S[B_GDEPTH * PLANE + p] = grad_out[channels + 1, y, x0 + l]
                deepest = max(deepest, n_last[y, x0 + l])
            for ch in range(channels):
                for l in range(TILE):
                    S[(B_GFEATURES + ch) * PLANE + _pixel(r, l)] = grad_out[ch, y, x0 + l]
        start = tile_start[tile]
        entry_grads[start + deepest:tile_start[tile + 1]] = zero  # entries no pixel reached
        for k in range(start + deepest - 1, start - 1, -1):
            E = entry_grads[k]
            g = tile_ids[k]
            mx, my, a, b, c = means2d[g, 0], means2d[g, 1], conic[g, 0], conic[g, 1], conic[g, 2]
            o, z = opacity[g], depth[g]
            f0, f1, f2 = _feature(features, g, 0, zero), _feature(features, g, 1, zero), \
                _feature(features, g, 2, zero)
            left = S[CENTRE_X * PLANE + _pixel(0, max(rects[g, 0] - x0, 0))]
            right = S[CENTRE_X * PLANE + _pixel(0, min(rects[g, 1] - x0, TILE - 1))]
            entry = _as_dtype(S, k - start)
            s_o = s_mx = s_my = s_a = s_b = s_c = s_z = s_f0 = s_f1 = s_f2 = zero
            for strip in range(STRIPS):
                lo, n = _run(rects, g, x0, y0, strip)
                if n == 0:
                    continue
                V = S[lo:]
                # g . v less its first three feature channels (added in the main loop)
                for l in range(n):
                    V[l + B_GV * PLANE] = V[l + B_GALPHA * PLANE] + V[l + B_GDEPTH * PLANE] * z
                for ch in range(3, c3, 3):
                    fa, fb, fc = _feature(features, g, ch, zero), _feature(features, g, ch + 1, zero), \
                        _feature(features, g, ch + 2, zero)
                    F = V[(B_GFEATURES + ch) * PLANE:]
                    for l in range(n):
                        V[l + B_GV * PLANE] += F[l] * fa + F[l + PLANE] * fb + F[l + 2 * PLANE] * fc
                for l in range(n):
                    px = V[l + CENTRE_X * PLANE]
                    dx = px - mx
                    dy = V[l + CENTRE_Y * PLANE] - my
                    power = half * (a * dx * dx + c * dy * dy) + b * dx * dy
                    e = exp_neg(power)
                    raw = o * e
                    alpha = min(max_alpha, raw)
                    act = ((px >= left) & (px <= right) & (entry < V[l + B_COUNT * PLANE]) & (power >= zero)
                           & (alpha >= min_alpha))
                    t_after = V[l + B_T * PLANE]
                    inv = one / (one - alpha)
                    t_before = t_after * inv
                    w = alpha * t_before if act else zero
                    g0 = V[l + B_GFEATURES * PLANE]
                    g1 = V[l + (B_GFEATURES + 1) * PLANE]
                    g2 = V[l + (B_GFEATURES + 2) * PLANE]
                    gv = V[l + B_GV * PLANE] + g0 * f0 + g1 * f1 + g2 * f2
                    d_alpha = t_before * gv - V[l + B_SUFFIX * PLANE] * inv
                    V[l + B_SUFFIX * PLANE] += w * gv
                    V[l + B_T * PLANE] = t_before if act else t_after
                    V[l + B_WEIGHT * PLANE] = w
                    s_z += w * V[l + B_GDEPTH * PLANE]
                    s_f0 += w * g0
                    s_f1 += w * g1
                    s_f2 += w * g2
                    d_alpha = d_alpha if act & (raw <= max_alpha) else zero  # capped: no gradient
                    s_o += d_alpha * (e if act else zero)
                    d_power = -d_alpha * alpha
                    s_mx -= d_power * (a * dx + b * dy)
                    s_my -= d_power * (b * dx + c * dy)
                    s_a += d_power * half * dx * dx
                    s_b += d_power * dx * dy
                    s_c += d_power * half * dy * dy
            for ch in range(3, c3, 3):  # further channels, three at a time
                s_fa = s_fb = s_fc = zero
                for strip in range(STRIPS):
                    lo, n = _run(rects, g, x0, y0, strip)
                    V = S[lo:]
                    F = V[(B_GFEATURES + ch) * PLANE:]
                    for l in range(n):
                        w = V[l + B_WEIGHT * PLANE]
                        s_fa += w * F[l]
                        s_fb += w * F[l + PLANE]
                        s_fc += w * F[l + 2 * PLANE]
                _set_feature(E, ch, s_fa, channels)
                _set_feature(E, ch + 1, s_fb, channels)
                _set_feature(E, ch + 2, s_fc, channels)
            _set_feature(E, 0, s_f0, channels)
            _set_feature(E, 1, s_f1, channels)
            _set_feature(E, 2, s_f2, channels)
            E[GRAD_MEANS2D] = s_mx
            E[GRAD_MEANS2D + 1] = s_my
            E[GRAD_CONIC] = s_a
            E[GRAD_CONIC + 1] = s_b
            E[GRAD_CONIC + 2] = s_c
            E[GRAD_OPACITY] = s_o
            E[GRAD_DEPTH] = s_z


@numba.njit(cache=True)
def sum_entries(tile_ids, entry_grads, grads):
    """grads[g] += entry_grads[k] for every list entry k of Gaussian g = tile_ids[k], in increasing k
    (serially: a fixed order of the sums). grads (M, 7 + C), zeros on entry."""
    for k in range(tile_ids.shape[0]):
        g = tile_ids[k]
        for c in range(grads.shape[1]):
            grads[g, c] += entry_grads[k, c]
