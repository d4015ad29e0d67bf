"""Device stable radix sort (numba.cuda), for the splatter when CuPy is not installed, and the prefix
sum it is built on.

    exclusive_scan(counts_d) -> (offsets_d, total)
        counts_d: (n,) int32 or int64 device array, n >= 0; offsets_d: a new (n,) int64 device array,
        offsets_d[i] = sum(counts_d[:i]); total = sum(counts_d), a Python int (the only value copied
        to the host).
    radix_sort(keys_d, values_d=None, key_bits=64) -> (keys_d, values_d or None)
        keys_d: (n,) int64 device array of keys >= 0, sorted by their low `key_bits` bits; values_d:
        an optional (n,) device array (the splatter's int32 ids) that moves with its key. Returns new
        device arrays; the inputs are not modified. Stable: equal keys keep their input order.

Host arrays are accepted too (copied to the device). stg_runtime.cuda.splat sorts its depth keys and
tile keys (keys only) with CuPy's sort when CuPy is there, else with radix_sort; it needs no scan of
its own (exclusive_scan is the radix sort's scan, exposed so that it is tested on its own). These
replace a bitonic sort (O(n log^2 n) work, one launch per step) and a Hillis-Steele scan over the
whole array.

Blocks: BLOCK = 256 threads, ITEMS = 4 consecutive elements per thread, so a block covers a tile of
TILE = 1024 elements. A block scan (used by both) is a Hillis-Steele inclusive scan of the threads'
totals in double-buffered shared memory: log2(BLOCK) steps with one barrier each (half of Blelloch's
barriers; its O(BLOCK log BLOCK) work is 2 operations per element at ITEMS = 4, so the work stays O(n)).

Scan: each block scans its tile (per-thread serial sums, the block scan, per-thread serial exclusive
sums) and writes its total to a block-sums array; the block sums are scanned by the same function
(recursively, until one block is left), then added back to their tile. O(n) work, 2 launches per
level above one, ceil(log_TILE (n + 1)) levels (one up to n = 1023, two up to 2^20 - 1). The total is
computed on the device as one extra element (index n) of the scan.

Radix sort: LSD, 4-bit digits (16 buckets), ceil(key_bits / 4) passes, double-buffered. Per pass:
(a) per-block digit histogram (shared-memory atomics), stored digit-major, hist[d * blocks + b];
(b) its exclusive scan (as above), so that starts[d * blocks + b] is where block b's elements of digit
d go; (c) a scatter: element -> starts[d * blocks + b] + its rank among the elements of digit d before
it in its tile. The rank needs no warp intrinsics: counts of the 16 digits are packed in 16-bit
fields, 4 per int64 word (4 words); each thread counts its items' digits, one 4-lane block scan gives
it the counts of every digit in the threads before it, and its items' ranks are read from the fields
of their digits (plus the earlier items of the same digit in its own thread). A tile has < 2^15
elements, so no field overflows. Work per pass O(n); launches per pass: 3, plus 2 per scan level
above one (the histogram has 16 ceil(n / TILE) entries: one level up to n = 65536, two up to 2^26). Total work
O(n key_bits / 4), no host copies. Why 4-bit digits: 8-bit ones halve the passes but need 256
histogram entries per block (a 16x larger histogram to scan) and 64 packed words per thread for the
rank; at 4 bits the rank costs one 4-lane block scan. The caller passes the bit length of the largest
key, so short keys (ranks, tile * K + rank) take few passes.

Under numba's simulator (NUMBA_ENABLE_CUDASIM=1, set before numba.cuda is first imported) the same
kernels run on the CPU, slowly: every thread of a block is a Python thread, and each barrier of each
block costs milliseconds, so keep n and the passes small there.
"""
from __future__ import annotations

import functools

import numpy as np
from numba import cuda

#: Threads per block.
BLOCK = 256
#: Consecutive elements per thread: a block covers BLOCK * ITEMS elements.
ITEMS = 4
_DIGIT_BITS = 4
_BUCKETS = 1 << _DIGIT_BITS
_LANES = _BUCKETS // 4  # packed-count words per thread: 4 fields of 16 bits each


def _blocks(n, tile):
    """Blocks of `tile` elements covering n elements (at least one)."""
    return max(1, -(-n // tile))


def _device(x, name):
    """x as a 1-D numba device array (device arrays as they are; host arrays copied)."""
    if hasattr(x, "copy_to_host"):
        d = x
    elif hasattr(x, "__cuda_array_interface__"):
        d = cuda.as_cuda_array(x)
    else:
        d = cuda.to_device(np.ascontiguousarray(x))
    if d.ndim != 1:
        raise ValueError(f"{name} must be 1-D, got shape {d.shape}")
    return d


@functools.lru_cache(maxsize=None)
def _kernels(block, items):
    """The kernels for blocks of `block` threads (a power of two, 2..1024) of `items` elements each:
    shared arrays need compile-time sizes, so each shape gets its own kernels (the tests use small
    ones)."""
    if block < 2 or block > 1024 or block & (block - 1):
        raise ValueError(f"block must be a power of two in [2, 1024], got {block}")
    if items < 1 or block * items >= 1 << 15:
        raise ValueError(f"items must be >= 1 with block * items < 2^15, got {items}")
    B = block
    ITEMS_ = items
    TILE = block * items
    LANES = _LANES
    BUCKETS = _BUCKETS
    SCAN_SHARED = 2 * B  # shared array sizes must be constants in the kernels
    SORT_SHARED = 2 * LANES * B

    @cuda.jit(device=True)
    def block_scan(s, lanes, t):
        """Inclusive scan of `lanes` rows of B int64 held in buffer 0 of the shared array s (row l at
        s[l * B:(l + 1) * B]; buffer 1 follows at s[lanes * B:]). Returns the offset of the buffer
        that holds the result. Called by all threads of the block, after a barrier."""
        src = 0
        d = 1
        while d < B:
            dst = lanes * B - src
            for lane in range(lanes):
                v = s[src + lane * B + t]
                if t >= d:
                    v += s[src + lane * B + t - d]
                s[dst + lane * B + t] = v
            cuda.syncthreads()
            src = dst
            d *= 2
        return src

    @cuda.jit
    def scan_tiles(src, out, sums):
        """out[i] = the exclusive prefix sum of src within i's tile (src read as 0 past its end; out
        may be longer); sums[b] = tile b's total."""
        s = cuda.shared.array(SCAN_SHARED, np.int64)
        t = cuda.threadIdx.x
        b = cuda.blockIdx.x
        base = b * TILE + t * ITEMS_
        own = np.int64(0)
        for j in range(ITEMS_):
            if base + j < src.shape[0]:
                own += src[base + j]
        s[t] = own
        cuda.syncthreads()
        r = block_scan(s, 1, t)
        run = s[r + t] - own
        for j in range(ITEMS_):
            i = base + j
            if i < out.shape[0]:
                out[i] = run
            if i < src.shape[0]:
                run += src[i]
        if t == B - 1:
            sums[b] = s[r + t]

    @cuda.jit
    def add_offsets(out, offsets):
        """out[i] += offsets[i's tile]."""
        b = cuda.blockIdx.x
        if b > 0:
            base = b * TILE + cuda.threadIdx.x * ITEMS_
            for j in range(ITEMS_):
                if base + j < out.shape[0]:
                    out[base + j] += offsets[b]

    @cuda.jit
    def histogram(keys, shift, hist):
        """hist[d * blocks + b] = the number of keys of tile b whose digit (key >> shift) & 15 is d."""
        h = cuda.shared.array(BUCKETS, np.int32)
        t = cuda.threadIdx.x
        b = cuda.blockIdx.x
        nb = cuda.gridDim.x
        for d in range(t, BUCKETS, B):  # a block may have fewer threads than buckets
            h[d] = 0
        cuda.syncthreads()
        base = b * TILE + t * ITEMS_
        for j in range(ITEMS_):
            if base + j < keys.shape[0]:
                cuda.atomic.add(h, (keys[base + j] >> shift) & (BUCKETS - 1), np.int32(1))
        cuda.syncthreads()
        for d in range(t, BUCKETS, B):
            hist[d * nb + b] = h[d]

    @cuda.jit
    def scatter(keys, values, has_values, shift, starts, out_keys, out_values):
        """Each key (and value) to starts[digit * blocks + b] + its rank among the keys of its tile
        with the same digit before it (packed counts and a block scan, see the module docstring)."""
        s = cuda.shared.array(SORT_SHARED, np.int64)
        run = cuda.local.array(LANES, np.int64)
        t = cuda.threadIdx.x
        b = cuda.blockIdx.x
        nb = cuda.gridDim.x
        base = b * TILE + t * ITEMS_
        for lane in range(LANES):
            run[lane] = 0
        for j in range(ITEMS_):
            if base + j < keys.shape[0]:
                digit = (keys[base + j] >> shift) & (BUCKETS - 1)
                run[digit >> 2] += np.int64(1) << ((digit & 3) * 16)
        for lane in range(LANES):
            s[lane * B + t] = run[lane]
        cuda.syncthreads()
        r = block_scan(s, LANES, t)
        for lane in range(LANES):
            run[lane] = s[r + lane * B + t] - run[lane]  # the counts in the threads before this one
        for j in range(ITEMS_):
            i = base + j
            if i < keys.shape[0]:
                key = keys[i]
                digit = (key >> shift) & (BUCKETS - 1)
                word = digit >> 2
                field = (digit & 3) * 16
                dest = starts[digit * nb + b] + ((run[word] >> field) & 0xFFFF)
                run[word] += np.int64(1) << field
                out_keys[dest] = key
                if has_values:
                    out_values[dest] = values[i]

    @cuda.jit
    def copy(src, dst):
        base = cuda.blockIdx.x * TILE + cuda.threadIdx.x * ITEMS_
        for j in range(ITEMS_):
            if base + j < dst.shape[0]:
                dst[base + j] = src[base + j]

    return scan_tiles, add_offsets, histogram, scatter, copy


# The kernels of the default shape, by name (tools/check_cuda_kernels.py compiles module-level kernels).
_scan_tiles, _add_offsets, _histogram, _scatter, _copy = _kernels(BLOCK, ITEMS)


def _scan_into(src, out, block, items):
    """out (int64, len(out) >= len(src)) = the exclusive prefix sums of src, read as 0 past its end."""
    scan_tiles, add_offsets, _, _, _ = _kernels(block, items)
    nb = _blocks(out.shape[0], block * items)
    sums = cuda.device_array(nb, np.int64)
    scan_tiles[nb, block](src, out, sums)
    if nb > 1:
        offsets = cuda.device_array(nb, np.int64)
        _scan_into(sums, offsets, block, items)
        add_offsets[nb, block](out, offsets)


def exclusive_scan(counts_d, *, _block=BLOCK, _items=ITEMS):
    """(offsets, total): offsets[i] = sum(counts[:i]), a new int64 device array, and the total as a
    Python int. counts_d: a 1-D int32 or int64 device array (or host array), possibly empty. O(n)
    work, 2 launches per level of ceil(log_TILE (n + 1)); one int64 comes back to the host."""
    counts = _device(counts_d, "counts_d")
    if counts.dtype not in (np.int32, np.int64):
        raise TypeError(f"counts_d must be int32 or int64, got {counts.dtype}")
    n = counts.shape[0]
    out = cuda.device_array(n + 1, np.int64)  # out[n]: the total
    _scan_into(counts, out, _block, _items)
    total = int(out[n:n + 1].copy_to_host()[0])
    return out[:n], total


def radix_sort(keys_d, values_d=None, key_bits=64, *, _block=BLOCK, _items=ITEMS):
    """(keys, values): keys_d (1-D int64, >= 0) stably sorted by their low `key_bits` bits, and
    values_d (1-D, same length; optional, else None) in the same order, as new device arrays.

    ceil(key_bits / 4) passes: pass the bit length of the largest key (key_bits=0: a copy). Keys with
    bits at or above key_bits are ordered by their low bits only; negative keys (which the splatter
    never makes) are ordered as their two's-complement bits, so only with key_bits=64, after the rest.
    """
    keys = _device(keys_d, "keys_d")
    if keys.dtype != np.int64:
        raise TypeError(f"keys_d must be int64, got {keys.dtype}")
    key_bits = int(key_bits)
    if not 0 <= key_bits <= 64:
        raise ValueError(f"key_bits must be in [0, 64], got {key_bits}")
    n = keys.shape[0]
    values = None
    if values_d is not None:
        values = _device(values_d, "values_d")
        if values.shape[0] != n:
            raise ValueError(f"values_d has {values.shape[0]} elements, keys_d {n}")
    _, _, histogram, scatter, copy = _kernels(_block, _items)
    nb = _blocks(n, _block * _items)
    key_buf = [cuda.device_array(n, np.int64) for _ in range(2)]
    val_buf = [cuda.device_array(n, values.dtype) for _ in range(2)] if values is not None else [None, None]
    passes = -(-key_bits // _DIGIT_BITS)
    if n <= 1 or passes == 0:
        if n:
            copy[nb, _block](keys, key_buf[0])
            if values is not None:
                copy[nb, _block](values, val_buf[0])
        return key_buf[0], val_buf[0]
    hist = cuda.device_array(_BUCKETS * nb, np.int32)
    starts = cuda.device_array(_BUCKETS * nb, np.int64)
    dummy = cuda.device_array(1, np.int32)  # the values kernel argument when there are none
    src_k, src_v = keys, values
    for p in range(passes):
        shift = p * _DIGIT_BITS
        dst_k, dst_v = key_buf[p & 1], val_buf[p & 1]
        histogram[nb, _block](src_k, shift, hist)
        _scan_into(hist, starts, _block, _items)
        scatter[nb, _block](src_k, dummy if values is None else src_v, values is not None, shift, starts,
                            dst_k, dummy if values is None else dst_v)
        src_k, src_v = dst_k, dst_v
    return src_k, src_v
