"""Fast CPU splatter (numba): the rules of formats/stg-v1.md, section 3, tile by tile.

    rasterize(means, quats, scales, opacities, features, camera, *, tile_size=16)
        -> features (H, W, C), alpha (H, W), depth (H, W), all float32

Same semantics as stg_runtime.spec.rasterize_oracle (the float64 transcription of the spec); the
results agree with it to float32 rounding. The pipeline, one numba kernel per step:

1. _project (parallel over Gaussians): stg_runtime.projection.footprint (shared with the GPU
   splatter, stg_runtime.cuda.splat), in float64: camera-space depth, the EWA 2D covariance's conic,
   and the rectangle of pixels to visit: the pixel centres within the 3-sigma radius (the spec's
   footprint) that can also reach alpha >= 1/255 (the bounding box of the ellipse power <=
   log(255 opacity), with a margin), clipped to the image. Culled Gaussians (near plane, determinant, opacity floor, nothing to visit)
   get no tiles. Each kept Gaussian gets a 64-byte record (see _PACKED): all the compositor reads
   about it.
2. sort_by_depth: the kept Gaussians in (depth, index) order (radix sort; exactly the float64 order).
3. bin_tiles (parallel over pieces of the depth order): every Gaussian is listed in each tile its
   rectangle meets; lists come out in depth order.
4. _composite (parallel over tiles, taken longest list first from an atomic counter): a tile's state
   (transmittance, sum w z, sum w f per channel) lives in planes of one array, each plane laid out in
   strips 8 pixels wide, row-major within a strip. Per Gaussian and strip, the pixels from the first
   to the last of its rectangle are one run, rounded up to 16 pixels, composited by one branch-free
   loop that LLVM vectorises (8 float32 lanes), with the first three feature channels (all nine of
   a full model; further channels then three at a time, from the run's weights); pixels outside the
   rectangle, stopped pixels and skipped contributions are masked. exp is a vectorisable polynomial (relative error ~1e-7; numba
   cannot vectorise libm's expf without SVML). Rows where every pixel has stopped are left out of
   the runs, and a tile ends once all its pixels have stopped. Records are read by Gaussian id, a
   few list entries ahead of use (prefetch), which makes a depth-ordered copy of them unnecessary.

stage_seconds() times the steps (bench/render.py prints them).

Every per-pixel decision depends only on the pixel and the Gaussian, never on the tile, and every
pixel takes the same instruction path, so images do not depend on tile_size (bit for bit).
"""
from __future__ import annotations

import time
from contextlib import contextmanager

import numba
import numpy as np
from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

from .camera import Camera
from .projection import camera_params, footprint
from .spec import MAX_ALPHA, MIN_ALPHA32, T_STOP32

#: The per-Gaussian record the compositor reads, float32, one 64-byte cache line: mean x, mean y
#: (pixels), conic A/2, B, C/2, opacity, depth z, thr = log(255 opacity) + 0.01 (alpha >= 1/255 needs
#: power <= thr), the pixel rectangle u0, u1, v0, v1 (inclusive, integers), the first 3 feature
#: channels (0 if fewer), 0.
_PACKED = 16
#: Pixels per vector (float32 lanes of AVX2) and the width of a strip of the compositor's tile state.
LANES = 8
#: Runs are rounded up to this many pixels, so that no pixel takes LLVM's scalar remainder loop
#: (measured faster than rounding to LANES).
_STEP = 2 * LANES
#: How many list entries ahead the compositor prefetches a Gaussian's record.
_AHEAD = 4
#: Largest tile_size, and the length of each plane of the compositor's per-tile state.
MAX_TILE = 64
_PLANE = MAX_TILE * MAX_TILE + _STEP


# exp(f) on |f| <= ln(2)/2: Chebyshev interpolant of degree 6 (relative error 2.5e-9; ~1e-7 once
# evaluated in float32). ln 2 is split so that n * _LN2_HI is exact for |n| < 2^15 (Cody and Waite).
_E0, _E1, _E2, _E3 = 1.0, 1.0000000379432996, 0.500000004740163, 0.16666414507167096
_E4, _E5, _E6 = 0.0416663516378278, 0.008375210201056223, 0.0013941213136701553
_LN2_HI, _LN2_LO = 0.693359375, -2.1219444005469057e-4


@intrinsic
def _pow2(typingctx, n):
    """2**n as float32 for an integer-valued float32 n in [-126, 127], built from the exponent bits
    (a bit cast, which numba cannot spell; unlike ldexp it vectorises)."""
    if n != types.float32:
        return None

    def codegen(context, builder, signature, args):
        i32 = ir.IntType(32)
        k = builder.fptosi(args[0], i32)
        bits = builder.shl(builder.add(k, ir.Constant(i32, 127)), ir.Constant(i32, 23))
        return builder.bitcast(bits, ir.FloatType())

    return types.float32(types.float32), codegen


@intrinsic
def _prefetch(typingctx, arr, index):
    """Ask the CPU to start loading the cache line of arr.flat[index] (no effect on results)."""
    if not isinstance(arr, types.Array) or not isinstance(index, types.Integer):
        return None

    def codegen(context, builder, signature, args):
        data = context.make_array(signature.args[0])(context, builder, args[0]).data
        i8p = ir.IntType(8).as_pointer()
        i32 = ir.IntType(32)
        fn = cgutils.get_or_insert_function(
            builder.module, ir.FunctionType(ir.VoidType(), [i8p, i32, i32, i32]), "llvm.prefetch.p0")
        address = builder.bitcast(builder.gep(data, [args[1]]), i8p)
        builder.call(fn, [address, ir.Constant(i32, 0), ir.Constant(i32, 3), ir.Constant(i32, 1)])
        return context.get_dummy_value()

    return types.none(arr, index), codegen


@intrinsic
def _fetch_add(typingctx, arr, index, value):
    """Atomically arr[index] += value for an int64 array; returns the previous value."""
    if not (isinstance(arr, types.Array) and arr.dtype == types.int64 and isinstance(index, types.Integer)
            and isinstance(value, types.Integer)):
        return None

    def codegen(context, builder, signature, args):
        data = context.make_array(signature.args[0])(context, builder, args[0]).data
        value = context.cast(builder, args[2], signature.args[2], types.int64)
        return builder.atomic_rmw("add", builder.gep(data, [args[1]]), value, "monotonic")

    return types.int64(arr, index, value), codegen


@numba.njit(inline="always")
def exp_neg(p):
    """exp(-p) for float32 p <= 87 (larger p is clamped: the result is then < 2e-38); relative error
    below 2e-7. Branch-free: Cody-Waite reduction, a polynomial, and the exponent bits."""
    x = -min(p, np.float32(87.0))
    n = np.floor(x * np.float32(1.4426950408889634) + np.float32(0.5))
    f = (x - n * np.float32(_LN2_HI)) - n * np.float32(_LN2_LO)
    r = np.float32(_E6)
    r = r * f + np.float32(_E5)
    r = r * f + np.float32(_E4)
    r = r * f + np.float32(_E3)
    r = r * f + np.float32(_E2)
    r = r * f + np.float32(_E1)
    r = r * f + np.float32(_E0)
    return r * _pow2(n)


@numba.njit(inline="always", fastmath={"contract"})
def _blend(px, py, t, mx, my, ha, cb, hc, o, left, right, bottom):
    """One pixel (centre px, py; transmittance t, negative once stopped) and one Gaussian (mean mx, my;
    conic A/2 = ha, B = cb, C/2 = hc; opacity o) inside the rectangle [left, right] x [.., bottom] of
    pixel centres: the spec's rules, branch-free. Returns (weight w = alpha T or 0, the new t, whether
    the pixel stopped here)."""
    zero = np.float32(0.0)
    dx = px - mx
    dy = py - my
    power = dx * (ha * dx + cb * dy) + hc * dy * dy
    alpha = min(np.float32(MAX_ALPHA), o * exp_neg(power))
    ok = ((px >= left) & (px <= right) & (py <= bottom) & (t > zero) & (power >= zero)
          & (alpha >= MIN_ALPHA32))
    t_next = t * (np.float32(1.0) - alpha)
    stop = ok & (t_next < T_STOP32)
    add = ok & (t_next >= T_STOP32)
    w = alpha * t if add else zero
    return w, (t_next if add else (-t if stop else t)), stop


_footprint = numba.njit(inline="always")(footprint)


@numba.njit(parallel=True, cache=True)
def _project(means, quats, scales, opacities, features, cam, width, height, tile_size, packed, tiles, depth):
    """Per Gaussian i (stg_runtime.projection.footprint; cam as projection.camera_params):
    packed[i] = its record (see _PACKED); tiles[i] = [tx0, tx1, ty0, ty1], the inclusive range of tiles
    its pixel rectangle meets (tx0 > tx1 when culled); depth[i] = its camera-space z (float64, for
    sorting)."""
    for i in numba.prange(means.shape[0]):
        z, u, v, ca, cb, cc, thr, u0, u1, v0, v1 = _footprint(cam, width, height, means, quats, scales, opacities, i)
        depth[i] = z
        if u0 > u1:
            tiles[i, 0] = 1
            tiles[i, 1] = 0
            tiles[i, 2] = 1
            tiles[i, 3] = 0
            continue
        tiles[i, 0] = u0 // tile_size
        tiles[i, 1] = u1 // tile_size
        tiles[i, 2] = v0 // tile_size
        tiles[i, 3] = v1 // tile_size
        packed[i, 0] = u
        packed[i, 1] = v
        packed[i, 2] = ca
        packed[i, 3] = cb
        packed[i, 4] = cc
        packed[i, 5] = opacities[i]
        packed[i, 6] = z
        packed[i, 7] = thr
        packed[i, 8] = u0
        packed[i, 9] = u1
        packed[i, 10] = v0
        packed[i, 11] = v1
        for j in range(3):
            packed[i, 12 + j] = features[i, j] if j < features.shape[1] else 0.0
        packed[i, 15] = 0.0


@numba.njit(cache=True)
def sort_by_depth(tiles, depth):
    """Ids of the kept Gaussians (non-empty tiles) in (depth, index) order.

    A stable LSD radix sort (11-bit digits) on the bits of float32(depth) (monotonic for positive
    floats), then each run of equal float32 keys is put in float64 order by a stable insertion sort:
    since rounding to float32 is monotonic, that is exactly the float64 (depth, index) order."""
    m = tiles.shape[0]
    n = 0
    for i in range(m):
        n += tiles[i, 0] <= tiles[i, 1]
    src_i = np.empty(n, np.int64)
    src_k = np.empty(n, np.uint32)
    j = 0
    for i in range(m):
        if tiles[i, 0] <= tiles[i, 1]:
            src_i[j] = i
            src_k[j] = np.float32(depth[i]).view(np.uint32)
            j += 1
    dst_k = np.empty_like(src_k)
    dst_i = np.empty_like(src_i)
    count = np.empty(2048, np.int64)
    for shift in (0, 11, 22):
        count[:] = 0
        for j in range(n):
            count[(src_k[j] >> shift) & 2047] += 1
        if n == 0 or count[(src_k[0] >> shift) & 2047] == n:
            continue
        total = 0
        for d in range(2048):
            cnt = count[d]
            count[d] = total
            total += cnt
        for j in range(n):
            d = (src_k[j] >> shift) & 2047
            pos = count[d]
            count[d] = pos + 1
            dst_k[pos] = src_k[j]
            dst_i[pos] = src_i[j]
        src_k, dst_k = dst_k, src_k
        src_i, dst_i = dst_i, src_i
    j = 1
    while j < n:
        if src_k[j] != src_k[j - 1]:
            j += 1
            continue
        a = j - 1  # a run [a, b) of equal float32 keys
        b = j + 1
        while b < n and src_k[b] == src_k[a]:
            b += 1
        for q in range(a + 1, b):
            g = src_i[q]
            r = q
            while r > a and depth[src_i[r - 1]] > depth[g]:
                src_i[r] = src_i[r - 1]
                r -= 1
            src_i[r] = g
        j = b
    return src_i


def bin_tiles(order, tiles, tiles_x, tiles_y):
    """Per-tile lists of the kept Gaussians, in depth order: order (K,) their ids in (depth, index)
    order, tiles (M, 4) as made by _project.

    Returns tile_start (tiles + 1,) int64, tile_ids (entries,) int32 (tile t lists the Gaussian ids
    tile_ids[tile_start[t]:tile_start[t + 1]], front to back), and the tiles ordered by decreasing
    list length (the compositor's work order). `order` is cut into one piece per thread: each piece
    counts its entries per tile, then writes them after those of the pieces before it (in depth order)
    within each tile's list, so the lists are the same whatever the number of threads."""
    pieces = max(1, min(numba.get_num_threads(), order.shape[0] // 4096))
    return _bin_tiles(order, tiles, tiles_x, tiles_y, pieces)


@numba.njit(inline="always")
def _list_piece(order, tiles, tiles_x, lo, hi, cursor, tile_ids, write):
    """Walk the ids order[lo:hi] and, for each tile t their rectangles meet, advance cursor[t]; with
    `write`, first store the id at tile_ids[cursor[t]] (without, the walk only counts)."""
    n = order.shape[0]
    for i in range(lo, hi):
        if i + 16 < n:
            _prefetch(tiles, order[i + 16] * 4)
        g = order[i]
        for ty in range(tiles[g, 2], tiles[g, 3] + 1):
            for tx in range(tiles[g, 0], tiles[g, 1] + 1):
                t = ty * tiles_x + tx
                if write:
                    tile_ids[cursor[t]] = g
                cursor[t] += 1


@numba.njit(parallel=True, cache=True)
def _bin_tiles(order, tiles, tiles_x, tiles_y, pieces):
    """bin_tiles with `order` cut into `pieces` pieces."""
    n = order.shape[0]
    n_tiles = tiles_x * tiles_y
    size = -(-n // pieces)
    counts = np.zeros((pieces, n_tiles), np.int64)
    no_ids = np.empty(0, np.int32)
    for c in numba.prange(pieces):
        _list_piece(order, tiles, tiles_x, c * size, min(n, (c + 1) * size), counts[c], no_ids, False)
    tile_start = np.empty(n_tiles + 1, np.int64)
    total = 0
    for t in range(n_tiles):  # each piece's cursor: where its entries of tile t begin
        tile_start[t] = total
        for c in range(pieces):
            cnt = counts[c, t]
            counts[c, t] = total
            total += cnt
    tile_start[n_tiles] = total
    tile_ids = np.empty(total, np.int32)
    for c in numba.prange(pieces):
        _list_piece(order, tiles, tiles_x, c * size, min(n, (c + 1) * size), counts[c], tile_ids, True)
    tile_order = np.argsort(tile_start[:-1] - tile_start[1:], kind="mergesort")
    return tile_start, tile_ids, tile_order


@numba.njit(parallel=True, cache=True, fastmath={"contract"})
def _composite(packed, feat, channels, tile_start, tile_ids, tile_order, tile_size, tiles_x, width,
               height, n_workers, out_f, out_a, out_d):
    """Composite every tile front to back (spec section 3) into out_f (H * W * channels), out_a (H * W),
    out_d (H * W): flat views of the (H, W, C), (H, W) images.

    packed (M, _PACKED), feat (M, C3: channels zero-padded to a multiple of 3; M x 0 when there are
    at most 3): per Gaussian id; tile t lists the ids tile_ids[tile_start[t]:tile_start[t + 1]],
    front to back.
    n_workers workers (one per thread) keep their buffers and take the tiles one at a time, in the
    order tile_order, from a shared atomic counter. A tile's state is stored strip by strip (strips
    LANES pixels wide when tile_size is a multiple of LANES, else one strip), each strip row-major,
    so that a Gaussian's run from the first to the last pixel of its rectangle in a strip wastes few
    lanes."""
    n_tiles = tile_start.shape[0] - 1
    c3 = max(3, feat.shape[1])
    sw = LANES if tile_size % LANES == 0 else tile_size  # strip width
    n_strips = tile_size // sw
    strip_pix = tile_size * sw
    n_pix = tile_size * tile_size
    plane = _PLANE  # a compile-time constant: LLVM then sees the planes cannot overlap in a run
    one = np.float32(1.0)
    zero = np.float32(0.0)
    half = np.float32(0.5)
    next_tile = np.zeros(1, np.int64)
    for worker in numba.prange(n_workers):
        # The tile's state, planes of one array: transmittance T (negated once the pixel has
        # stopped), sum w z, the current Gaussian's weights (for channels beyond 3), the pixel
        # centres x and y, then sum w f per channel.
        S = np.zeros((5 + c3) * plane, np.float32)
        T = S[:plane]
        D = S[plane:2 * plane]
        px = S[3 * plane:4 * plane]  # pixel centres (beyond the tile for the padding)
        py = S[4 * plane:5 * plane]
        F = S[5 * plane:]
        live = np.empty(n_strips * tile_size, np.bool_)  # strip rows with a pixel not yet stopped
        dead = np.empty(n_strips, np.bool_)  # whether a strip has a row where all pixels stopped
        while True:
            i = _fetch_add(next_tile, 0, 1)
            if i >= n_tiles:
                break
            tile = tile_order[i]
            x0 = (tile % tiles_x) * tile_size
            y0 = (tile // tiles_x) * tile_size
            x1 = min(x0 + tile_size, width) - 1
            y1 = min(y0 + tile_size, height) - 1
            n_live = 0
            dead[:] = False
            for q in range(n_strips * tile_size):
                live[q] = x0 + (q // tile_size) * sw <= x1 and y0 + q % tile_size <= y1
                n_live += live[q]
            used = n_pix + _STEP  # the part of each plane a run can reach
            T[:used] = one
            D[:used] = zero
            for ch in range(c3):
                F[ch * plane:ch * plane + used] = zero
            p = 0
            for strip in range(n_strips):
                for r in range(tile_size):
                    for c in range(sw):
                        px[p] = np.float32(x0 + strip * sw + c) + half
                        py[p] = np.float32(y0 + r) + half
                        p += 1
            px[n_pix:used] = np.float32(x0 + tile_size) + half  # the padding is beyond every rectangle
            py[n_pix:used] = np.float32(y0) + half
            k_end = tile_start[tile + 1]
            for k in range(tile_start[tile], k_end):
                if k + _AHEAD < k_end:
                    _prefetch(packed, tile_ids[k + _AHEAD] * _PACKED)
                g = tile_ids[k]
                mx = packed[g, 0]
                my = packed[g, 1]
                ha = packed[g, 2]
                cb = packed[g, 3]
                hc = packed[g, 4]
                o = packed[g, 5]
                z = packed[g, 6]
                f0 = packed[g, 12]
                f1 = packed[g, 13]
                f2 = packed[g, 14]
                ua = max(np.int64(packed[g, 8]), x0)
                ub = min(np.int64(packed[g, 9]), x1)
                vt = max(np.int64(packed[g, 10]), y0) - y0
                vb = min(np.int64(packed[g, 11]), y1) - y0
                for strip in range(n_strips):
                    sx0 = x0 + strip * sw
                    su0 = max(ua, sx0)
                    su1 = min(ub, sx0 + sw - 1)
                    if su0 > su1:
                        continue
                    # Rows of the rectangle in the strip, less those where every pixel has stopped.
                    r0 = vt
                    r1 = vb
                    if dead[strip]:
                        while r0 <= r1 and not live[strip * tile_size + r0]:
                            r0 += 1
                        while r1 >= r0 and not live[strip * tile_size + r1]:
                            r1 -= 1
                        if r0 > r1:
                            continue
                    # The run from pixel (su0, r0) to (su1, r1) of the strip, rounded up to whole
                    # steps; pixels outside the rectangle are masked by their centres.
                    start = strip * strip_pix + r0 * sw + su0 - sx0
                    end = strip * strip_pix + r1 * sw + su1 - sx0 + 1
                    end = start + (end - start + _STEP - 1) // _STEP * _STEP
                    left = np.float32(su0) + half
                    right = np.float32(su1) + half
                    bottom = np.float32(y0 + r1) + half
                    any_stop = False
                    # One view starting at the run: the planes are then at constant offsets from it,
                    # which LLVM sees cannot overlap (no runtime aliasing checks), and l >= 0 needs no
                    # wraparound check, so the loop vectorises.
                    V = S[start:]
                    if c3 == 9:  # the full model's 9 channels: all in one loop
                        f3, f4, f5 = feat[g, 3], feat[g, 4], feat[g, 5]
                        f6, f7, f8 = feat[g, 6], feat[g, 7], feat[g, 8]
                        for l in range(end - start):
                            w, t, stop = _blend(V[l + 3 * _PLANE], V[l + 4 * _PLANE], V[l], mx, my, ha, cb, hc,
                                                o, left, right, bottom)
                            V[l] = t
                            V[l + _PLANE] += w * z
                            V[l + 5 * _PLANE] += w * f0
                            V[l + 6 * _PLANE] += w * f1
                            V[l + 7 * _PLANE] += w * f2
                            V[l + 8 * _PLANE] += w * f3
                            V[l + 9 * _PLANE] += w * f4
                            V[l + 10 * _PLANE] += w * f5
                            V[l + 11 * _PLANE] += w * f6
                            V[l + 12 * _PLANE] += w * f7
                            V[l + 13 * _PLANE] += w * f8
                            any_stop |= stop
                        c_done = 9
                    else:
                        for l in range(end - start):
                            w, t, stop = _blend(V[l + 3 * _PLANE], V[l + 4 * _PLANE], V[l], mx, my, ha, cb, hc,
                                                o, left, right, bottom)
                            V[l] = t
                            V[l + _PLANE] += w * z
                            V[l + 2 * _PLANE] = w  # for the further channels
                            V[l + 5 * _PLANE] += w * f0
                            V[l + 6 * _PLANE] += w * f1
                            V[l + 7 * _PLANE] += w * f2
                            any_stop |= stop
                        c_done = 3
                    for ch in range(c_done, c3, 3):  # further channels, three at a time
                        fa = feat[g, ch]
                        fb = feat[g, ch + 1]
                        fc = feat[g, ch + 2]
                        Fv = V[(5 + ch) * _PLANE:]
                        for l in range(end - start):
                            Fv[l] += V[l + 2 * _PLANE] * fa
                            Fv[l + _PLANE] += V[l + 2 * _PLANE] * fb
                            Fv[l + 2 * _PLANE] += V[l + 2 * _PLANE] * fc
                    if any_stop:
                        n_cols = min(sw, x1 - sx0 + 1)
                        for r in range(r0, r1 + 1):
                            done = live[strip * tile_size + r]
                            for c in range(n_cols):
                                done &= T[strip * strip_pix + r * sw + c] < zero
                            if done:
                                live[strip * tile_size + r] = False
                                dead[strip] = True
                                n_live -= 1
                if n_live == 0:
                    break
            # Write out, a strip row at a time (flat outputs, unsigned indices: vectorised).
            for strip in range(n_strips):
                u0 = x0 + strip * sw
                n = min(sw, x1 - u0 + 1)
                for r in range(min(tile_size, y1 - y0 + 1)):
                    if n <= 0:
                        break
                    src = np.uint64(strip * strip_pix + r * sw)
                    dst = np.uint64((y0 + r) * width + u0)
                    for c in range(np.uint64(0), np.uint64(n)):
                        a = one - abs(T[src + c])
                        out_a[dst + c] = a
                        out_d[dst + c] = D[src + c] / a if a > zero else zero
                    for ch in range(channels):
                        uch = np.uint64(ch)
                        uchp = np.uint64(ch * plane)
                        uc = np.uint64(channels)
                        for c in range(np.uint64(0), np.uint64(n)):
                            out_f[(dst + c) * uc + uch] = F[uchp + src + c]


_STAGES: list = []  # the dict of an open stage_seconds() block


@contextmanager
def stage_seconds(clock=time.perf_counter):
    """Within the block, rasterize adds each step's seconds by `clock` (wall-clock by default;
    time.process_time: the process's CPU time) to the yielded dict (keys "project", "sort", "bin",
    "composite"), as stg_runtime.cuda.splat.stage_seconds does on the GPU."""
    times: dict = {}
    _STAGES.append((times, clock))
    try:
        yield times
    finally:
        _STAGES.remove((times, clock))


def _lap(name: str, since: float) -> float:
    """Inside stage_seconds(): add the seconds since `since` to step `name`; the time now."""
    if not _STAGES:
        return since
    times, clock = _STAGES[-1]
    now = clock()
    times[name] = times.get(name, 0.0) + now - since
    return now


def _aligned_empty(shape, align=64):
    """An uninitialised float32 array whose data starts on an `align`-byte boundary."""
    n = int(np.prod(shape))
    raw = np.empty(n + align // 4, np.float32)
    skip = (-raw.ctypes.data % align) // 4
    return raw[skip:skip + n].reshape(shape)


def _as_f32(x, shape):
    return np.ascontiguousarray(np.asarray(x, dtype=np.float32).reshape(shape))


def rasterize(means, quats, scales, opacities, features, camera: Camera, *, tile_size: int = 16):
    """Render M Gaussians with the rules of formats/stg-v1.md, section 3.

    means (M, 3) world positions; quats (M, 4) wxyz (normalised here; zero = identity); scales (M, 3)
    standard deviations (world units); opacities (M,); features (M, C), C >= 1; camera: Camera.
    Inputs are converted to float32. tile_size (pixels) changes speed only, never the image.
    Returns (features (H, W, C), alpha (H, W), depth (H, W)), float32, C-contiguous:
    F = sum w_i f_i, alpha = 1 - T_final, depth = sum w_i z_i / alpha (camera-space z; 0 where
    alpha == 0), with w_i = alpha_i T_i.
    """
    means = _as_f32(means, (-1, 3))
    m = means.shape[0]
    quats = _as_f32(quats, (m, 4))
    scales = _as_f32(scales, (m, 3))
    opacities = _as_f32(opacities, (m,))
    features = np.asarray(features)
    features = _as_f32(features, (m, features.shape[-1] if features.ndim == 2 else -1))
    tile_size = int(tile_size)
    if not 1 <= tile_size <= MAX_TILE:
        raise ValueError(f"tile_size must be in 1..{MAX_TILE}, got {tile_size}")
    W, H, C = camera.width, camera.height, features.shape[1]
    if C < 1:
        raise ValueError("features need at least one channel")
    packed_all = _aligned_empty((m, _PACKED))
    tiles_all = np.empty((m, 4), np.int32)
    depth = np.empty(m, np.float64)
    threads = numba.get_num_threads()
    lap = _STAGES[-1][1]() if _STAGES else 0.0
    with numba.parallel_chunksize(2048):  # dynamic scheduling: robust to a busy core
        _project(means, quats, scales, opacities, features, camera_params(camera), W, H, tile_size,
                 packed_all, tiles_all, depth)
    lap = _lap("project", lap)
    order = sort_by_depth(tiles_all, depth)
    lap = _lap("sort", lap)
    tiles_x = -(-W // tile_size)
    tiles_y = -(-H // tile_size)
    tile_start, tile_ids, tile_order = bin_tiles(order, tiles_all, tiles_x, tiles_y)
    lap = _lap("bin", lap)
    if C > 3:  # the further channels, zero-padded to a multiple of 3
        feat = np.zeros((m, -(-C // 3) * 3), np.float32)
        feat[:, :C] = features
    else:
        feat = np.empty((m, 0), np.float32)
    out_f = np.empty((H, W, C), np.float32)
    out_a = np.empty((H, W), np.float32)
    out_d = np.empty((H, W), np.float32)
    _composite(packed_all, feat, C, tile_start, tile_ids, tile_order, tile_size, tiles_x, W, H,
               max(1, min(threads, tiles_x * tiles_y)), out_f.reshape(-1), out_a.reshape(-1),
               out_d.reshape(-1))
    _lap("composite", lap)
    return out_f, out_a, out_d
