"""GPU splatter (numba.cuda): the rules of formats/stg-v1.md, section 3, with splat_cpu's contract.

    rasterize(means, quats, scales, opacities, features, camera, *, tile_size=16, out="host",
              sort="auto", workspace=None) -> features (H, W, C), alpha (H, W), depth (H, W), float32

Inputs may be host (numpy) or device arrays; with out="device" the results stay on the device. The
pipeline (everything stays on the device, except where said):

1. _project (one thread per Gaussian): as splat_cpu._project, in float64: camera-space depth, the EWA
   2D covariance and conic, the 3-sigma radius, and the rectangle of pixel centres within the radius
   that can reach alpha >= 1/255, clipped to the image; a record of 7 float32 (mean u, v, conic A/2,
   B, C/2, opacity, z), the rectangle (4 int32), the number of tiles it meets (0: culled) and a depth
   key, (float32 z bits << 32) | index (z = +inf when culled). Each block adds its tile count and its
   number of kept Gaussians K to two device counters, which are the only values copied to the host.
   The same launch clears the tile ranges.
2. Depth order: the depth keys sorted (CuPy's sort in place; without CuPy, or with sort="numba",
   stg_runtime.cuda.sort's radix sort). Positive floats and +inf order as their bits, so this is the
   order of increasing float32 z, ties (in float32) by index, culled Gaussians last.
3. _duplicate (one thread per rank r < K): one key tile * K + r per tile the Gaussian meets; blocks
   take their places in the key array from a third counter. The keys are unique, int32 when they
   fit (else int64), and sorting them gives every tile's list front to back; _ranges finds each
   tile's [start, end) and the Gaussian ids.
4. _composite (one block per tile, one thread per pixel): Gaussians are loaded in batches of one per
   thread into shared memory and composited front to back with the spec's skip and stop rules in
   float32 (as splat_cpu: the pixel rectangle is the footprint test). Features are accumulated in
   registers, up to CHANNELS_PER_PASS channels per launch (more channels: more passes over the same
   lists; one kernel is compiled per channel count, so its loops unroll). A block ends once all its
   pixels have stopped (syncthreads_count).

What a frame costs on the host matters as much as the kernels (docs/performance.md measures both): buffers are
kept in a Workspace between frames (stg_runtime.cuda.memory), launches repeat with the same arrays and
go through stg_runtime.cuda.launch, the camera is passed by value (camera_params), and the host waits
for the device once, for the two counters.
stage_seconds() times the steps (bench/render.py prints them).

Colour on the device: stg_runtime.cuda.decoder; time evaluation: stg_runtime.cuda.timeeval.

Under numba's simulator (NUMBA_ENABLE_CUDASIM=1, set before numba.cuda is first imported) the same
kernels run on the CPU, slowly: the tests use it on tiny images.
"""
from __future__ import annotations

import functools
import math
import time
from contextlib import contextmanager

import numpy as np
from numba import cuda

from ..camera import Camera
from ..projection import camera_params, footprint
from ..spec import MAX_ALPHA32, MIN_ALPHA32, T_STOP32
from . import sort as device_sort
from .device import cupy as _cupy
from .device import is_device_array, require, simulated
from .launch import launch
from .memory import Buffer, Workspace, device_f32
from .minmax import dmin

#: cuda.sort's block shape: its defaults on a GPU; under the simulator, where every barrier of every
#: block costs milliseconds, small blocks (the same kernels; tests/runtime/cuda/test_sort.py covers both).
_SORT_SHAPE: dict = {"_block": 8, "_items": 4} if simulated() else {}

#: Feature channels accumulated per compositing launch (registers per thread).
CHANNELS_PER_PASS = 16
#: Largest tile_size: a block has tile_size^2 threads, and its shared memory batch holds that many
#: Gaussians (12 KiB at 16).
MAX_TILE = 16
_BATCH = MAX_TILE * MAX_TILE


_footprint = cuda.jit(device=True, inline=True)(footprint)


@cuda.jit
def _project(means, quats, scales, opacities, cam, width, height, tile_size, packed, rect, counts, depth_bits,
             depth_ids, tile_range, counters):
    """Thread i: Gaussian i's record, rectangle and tile count (stg_runtime.projection.footprint; cam as
    projection.camera_params) and its depth key (depth_ids[i, 0] = i, and through the float32 view of the
    same memory depth_bits[i, 1] = z, +inf when culled); tile i's range set to empty (the grid covers
    max(M, number of tiles)). Per block: counters[0] += the tiles met, counters[1] += the Gaussians kept."""
    i = cuda.grid(1)
    if i < tile_range.shape[0]:
        tile_range[i, 0] = 0
        tile_range[i, 1] = 0
    n = 0
    if i < means.shape[0]:
        z, u, v, ca, cb, cc, _, u0, u1, v0, v1 = _footprint(cam, width, height, means, quats, scales, opacities, i)
        depth_ids[i, 0] = i
        depth_bits[i, 1] = math.inf
        if u0 <= u1:
            rect[i, 0] = u0
            rect[i, 1] = u1
            rect[i, 2] = v0
            rect[i, 3] = v1
            n = (u1 // tile_size - u0 // tile_size + 1) * (v1 // tile_size - v0 // tile_size + 1)
            depth_bits[i, 1] = z
            packed[i, 0] = u
            packed[i, 1] = v
            packed[i, 2] = ca
            packed[i, 3] = cb
            packed[i, 4] = cc
            packed[i, 5] = opacities[i]
            packed[i, 6] = z
        counts[i] = n
    block_tiles = cuda.shared.array(1, np.int64)
    if cuda.threadIdx.x == 0:
        block_tiles[0] = 0
    cuda.syncthreads()
    if n > 0:
        cuda.atomic.add(block_tiles, 0, n)
    kept = cuda.syncthreads_count(np.int32(1) if n > 0 else np.int32(0))  # (also the barrier for the sum)
    if cuda.threadIdx.x == 0 and kept > 0:
        cuda.atomic.add(counters, 0, block_tiles[0])
        cuda.atomic.add(counters, 1, kept)


@cuda.jit
def _clear(counters):
    i = cuda.grid(1)
    if i < counters.shape[0]:
        counters[i] = 0


@cuda.jit
def _duplicate(order, counts, rect, tile_size, tiles_x, counters, keys):
    """Thread r < K (K = counters[1], the Gaussians kept; order[r, 0] the id of the r-th nearest): one key
    tile * K + r per tile its rectangle meets, at places taken from counters[2] (per block; the keys
    are sorted next, so where each lands does not matter)."""
    r = cuda.grid(1)
    kept = counters[1]
    n = 0
    g = 0
    if r < kept:
        g = order[r, 0]
        n = counts[g]
    block = cuda.shared.array(2, np.int64)  # the block's count so far, then its first place
    if cuda.threadIdx.x == 0:
        block[0] = 0
    cuda.syncthreads()
    mine = 0
    if n > 0:
        mine = cuda.atomic.add(block, 0, n)
    cuda.syncthreads()
    if cuda.threadIdx.x == 0 and block[0] > 0:
        block[1] = cuda.atomic.add(counters, 2, block[0])
    cuda.syncthreads()
    if n == 0:
        return
    k = block[1] + mine
    for ty in range(rect[g, 2] // tile_size, rect[g, 3] // tile_size + 1):
        for tx in range(rect[g, 0] // tile_size, rect[g, 1] // tile_size + 1):
            keys[k] = np.int64(ty * tiles_x + tx) * kept + r
            k += 1


@cuda.jit
def _ranges(keys, order, counters, tile_range, ids):
    """Over the first counters[0] sorted keys (grid-stride): tile_range[t] = [start, end) of tile t's
    entries, ids[e] the Gaussian of entry e (order[r, 0] for key tile * K + r, K = counters[1])."""
    total = counters[0]
    kept = counters[1]
    for e in range(cuda.grid(1), total, cuda.gridsize(1)):
        key = np.int64(keys[e])
        tile = key // kept
        ids[e] = order[key - tile * kept, 0]
        if e == 0 or np.int64(keys[e - 1]) // kept != tile:
            tile_range[tile, 0] = e
        if e == total - 1 or np.int64(keys[e + 1]) // kept != tile:
            tile_range[tile, 1] = e + 1


@functools.lru_cache(maxsize=None)
def _compositor(n_ch: int):
    """The compositing kernel for n_ch (1..CHANNELS_PER_PASS) channels per pass: with the count fixed
    when it is compiled, the per-pixel sums stay in registers and the loops over channels unroll."""

    @cuda.jit
    def composite(packed, rect, features, tile_range, ids, ch0, tiles_x, width, height, out_f, out_a, out_d):
        """Block = tile, thread = pixel: composite the tile's list front to back (spec section 3),
        channels ch0 .. ch0 + n_ch of features into out_f, plus out_a and out_d."""
        ts = cuda.blockDim.x
        n_threads = ts * cuda.blockDim.y
        tile = cuda.blockIdx.x
        tid = cuda.threadIdx.y * ts + cuda.threadIdx.x
        ix = (tile % tiles_x) * ts + cuda.threadIdx.x
        iy = (tile // tiles_x) * ts + cuda.threadIdx.y
        inside = ix < width and iy < height
        px = np.float32(ix) + np.float32(0.5)
        py = np.float32(iy) + np.float32(0.5)
        acc = cuda.local.array(n_ch, np.float32)
        for c in range(n_ch):
            acc[c] = np.float32(0.0)
        s_rec = cuda.shared.array((_BATCH, 7), np.float32)
        s_rect = cuda.shared.array((_BATCH, 4), np.int32)
        s_feat = cuda.shared.array((_BATCH, n_ch), np.float32)
        T = np.float32(1.0)
        D = np.float32(0.0)
        done = not inside
        start = tile_range[tile, 0]
        end = tile_range[tile, 1]
        for batch in range(start, end, n_threads):
            if cuda.syncthreads_count(np.int32(1) if done else np.int32(0)) == n_threads:
                break
            k = batch + tid
            if k < end:  # one Gaussian per thread into shared memory
                g = ids[k]
                for q in range(7):
                    s_rec[tid, q] = packed[g, q]
                for q in range(4):
                    s_rect[tid, q] = rect[g, q]
                for c in range(n_ch):
                    s_feat[tid, c] = features[g, ch0 + c]
            cuda.syncthreads()
            for j in range(dmin(n_threads, end - batch)):
                if done:
                    break
                if ix < s_rect[j, 0] or ix > s_rect[j, 1] or iy < s_rect[j, 2] or iy > s_rect[j, 3]:
                    continue
                dx = px - s_rec[j, 0]
                dy = py - s_rec[j, 1]
                power = dx * (s_rec[j, 2] * dx + s_rec[j, 3] * dy) + s_rec[j, 4] * dy * dy
                if power < np.float32(0.0):
                    continue
                alpha = dmin(MAX_ALPHA32, s_rec[j, 5] * math.exp(-power))
                if alpha < MIN_ALPHA32:
                    continue
                t_next = T * (np.float32(1.0) - alpha)
                if t_next < T_STOP32:
                    done = True
                    break
                w = alpha * T
                D += w * s_rec[j, 6]
                for c in range(n_ch):
                    acc[c] += w * s_feat[j, c]
                T = t_next
            cuda.syncthreads()  # the batch is read before the next one is loaded
        if inside:
            for c in range(n_ch):
                out_f[iy, ix, ch0 + c] = acc[c]
            a = np.float32(1.0) - T
            out_a[iy, ix] = a
            out_d[iy, ix] = D / a if a > np.float32(0.0) else np.float32(0.0)

    return composite


_composite = _compositor(CHANNELS_PER_PASS)  # (module level: tools/check_cuda_kernels.py compiles it)


_STAGES: list = []  # the dict of an open stage_seconds() block


@contextmanager
def stage_seconds():
    """Within the block, rasterize synchronises the device after each step and adds the step's
    wall-clock seconds to the yielded dict (keys "inputs", "project", "depth order", "tile keys",
    "tile sort", "ranges", "composite"); for benchmarks: the synchronisations cost time."""
    times: dict = {}
    _STAGES.append(times)
    try:
        yield times
    finally:
        _STAGES.remove(times)


def _lap(name: str, since: float) -> float:
    """Inside stage_seconds(): synchronise, add the seconds since `since` to step `name`; the time now."""
    if not _STAGES:
        return since
    cuda.synchronize()
    now = time.perf_counter()
    _STAGES[-1][name] = _STAGES[-1].get(name, 0.0) + now - since
    return now


def _blocks(n, threads=256):
    """(blocks, threads per block) for n threads: blocks of `threads`, fewer for small n."""
    threads = min(threads, max(32, -(-n // 32) * 32))
    return max(1, -(-n // threads)), threads


SORTS = ("auto", "cupy", "numba")


def _sorter(sort: str):
    """CuPy for sort "cupy" (an error without it) and "auto" (when installed), else None (cuda.sort)."""
    if sort not in SORTS:
        raise ValueError(f"sort must be one of {SORTS}, got {sort!r}")
    if sort == "numba":
        return None
    cupy = _cupy()
    if cupy is None and sort == "cupy":
        raise RuntimeError("sort='cupy': CuPy is not installed here (or this is numba's simulator); "
                           "use sort='auto' or 'numba'")
    return cupy


def _host_counts(counters: Buffer):
    """counters[0] (tile entries) and counters[1] (Gaussians kept) on the host: waits for the device."""
    host = counters.to_host()
    return int(host[0]), int(host[1])


def rasterize(means, quats, scales, opacities, features, camera: Camera, *, tile_size: int = 16,
              out: str = "host", sort: str = "auto", workspace: Workspace | None = None):
    """Render M Gaussians with the rules of formats/stg-v1.md, section 3, on the GPU.

    Same arguments and results as stg_runtime.splat_cpu.rasterize: means (M, 3), quats (M, 4) wxyz,
    scales (M, 3), opacities (M,), features (M, C): numpy or device arrays (converted to float32).
    tile_size in 1..MAX_TILE (16; pixels; speed only). Returns (features (H, W, C), alpha (H, W), depth (H, W))
    float32: numpy arrays, or numba device arrays with out="device". sort: the device sort, "cupy",
    "numba" (stg_runtime.cuda.sort) or "auto" (CuPy where installed); speed only. workspace: buffers
    kept between calls (see Workspace; with out="device" the results are its buffers); without one,
    every buffer is new.
    """
    require()
    cupy = _sorter(sort)
    if out not in ("host", "device"):
        raise ValueError(f"out must be 'host' or 'device', got {out!r}")
    tile_size = int(tile_size)
    if not 1 <= tile_size <= MAX_TILE:
        raise ValueError(f"tile_size must be in 1..{MAX_TILE}, got {tile_size}")
    if _STAGES:
        cuda.synchronize()  # the caller's work is not this call's
    lap = time.perf_counter()
    ws = workspace if workspace is not None else Workspace()
    means_d = device_f32(means, (-1, 3))
    m = means_d.shape[0]
    quats_d = device_f32(quats, (m, 4))
    scales_d = device_f32(scales, (m, 3))
    opac_d = device_f32(opacities, (m,))
    if not is_device_array(features):
        features = np.asarray(features)
    shape = tuple(features.shape)  # (the simulator's shapes take no negative index)
    C = shape[1] if len(shape) == 2 else (int(np.prod(shape)) // max(m, 1))
    if C < 1:
        raise ValueError("features need at least one channel")
    feat_d = device_f32(features, (m, C))
    W, H = camera.width, camera.height
    tiles_x = -(-W // tile_size)
    n_tiles = tiles_x * -(-H // tile_size)
    m1 = max(m, 1)
    packed = ws.buffer("records", (m1, 7), np.float32).device
    rect = ws.buffer("rectangles", (m1, 4), np.int32).device
    counts = ws.buffer("tile counts", (m1,), np.int32).device
    depth_keys = ws.buffer("depth keys", (m1,), np.int64)  # (z float32 bits << 32) | index
    depth_bits = depth_keys.view(np.float32, (m1, 2))
    depth_ids = depth_keys.view(np.int32, (m1, 2))
    tile_range = ws.buffer("tile ranges", (n_tiles, 2), np.int64).device
    counters = ws.buffer("counters", (3,), np.int64)
    out_f = ws.buffer("features", (H, W, C), np.float32).device
    out_a = ws.buffer("alpha", (H, W), np.float32).device
    out_d = ws.buffer("depth", (H, W), np.float32).device
    lap = _lap("inputs", lap)
    launch(_clear, 1, 32, counters.device)
    launch(_project, *_blocks(max(m, n_tiles)), means_d, quats_d, scales_d, opac_d, camera_params(camera), W, H,
           tile_size, packed, rect, counts, depth_bits, depth_ids, tile_range, counters.device)
    total, kept = _host_counts(counters)  # waits for the projection only
    lap = _lap("project", lap)
    if total:
        # Depth order: the keys (z bits, index) sorted; z >= 0 and +inf order as their bits, ties by index.
        if cupy is not None:
            depth_keys.cupy.sort()
            order = depth_ids
        else:
            order = device_sort.radix_sort(depth_keys.device, key_bits=63, **_SORT_SHAPE)[0]
            order = order.view(np.int32).reshape(m1, 2)
        lap = _lap("depth order", lap)
        # tile * kept + rank: for CuPy int32 keys (half its sort's work) when they fit (cuda.sort sorts
        # int64, by the keys' bit length).
        key_type = np.int32 if cupy is not None and n_tiles * kept <= 2**31 else np.int64
        keys = ws.buffer(f"tile keys {np.dtype(key_type).char}", (total,), key_type, at_least=True)
        ids = ws.buffer("ids", (total,), np.int32, at_least=True)
        launch(_duplicate, *_blocks(m), order, counts, rect, tile_size, tiles_x, counters.device, keys.device)
        lap = _lap("tile keys", lap)
        if cupy is not None:
            keys.cupy[:total].sort()
            sorted_keys = keys.device
        else:
            sorted_keys = device_sort.radix_sort(keys.device[:total], key_bits=int(n_tiles * kept - 1).bit_length(),
                                               **_SORT_SHAPE)[0]
        lap = _lap("tile sort", lap)
        launch(_ranges, min(-(-keys.shape[0] // 256), 4096), 256, sorted_keys, order, counters.device, tile_range,
               ids.device)
        lap = _lap("ranges", lap)
    else:
        ids = ws.buffer("ids", (1,), np.int32, at_least=True)
    for ch0 in range(0, C, CHANNELS_PER_PASS):
        launch(_compositor(min(CHANNELS_PER_PASS, C - ch0)), n_tiles, (tile_size, tile_size),
               packed, rect, feat_d, tile_range, ids.device, ch0, tiles_x, W, H, out_f, out_a, out_d)
    _lap("composite", lap)
    if out == "device":
        return out_f, out_a, out_d
    return out_f.copy_to_host(), out_a.copy_to_host(), out_d.copy_to_host()
