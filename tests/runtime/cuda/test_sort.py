"""stg_runtime.cuda.sort (device exclusive scan and stable LSD radix sort) against numpy: np.cumsum and
np.argsort(kind="stable"); stability is checked by carrying the original indices as the values.

Without a GPU the tests run in numba's CUDA simulator, which must be enabled before numba.cuda is first
imported: test_under_simulator runs this file again in a subprocess with NUMBA_ENABLE_CUDASIM=1, on
small arrays (the simulator runs every GPU thread in Python, and each barrier costs milliseconds). Small
blocks (the private _block/_items arguments) give many blocks and several scan levels at small sizes. On
a machine where numba sees a GPU the same tests run directly, on larger arrays, and the subprocess test
is skipped.
"""
from __future__ import annotations

import os

import numpy as np
import pytest

from stg_runtime.cuda import sort as sort_cuda
from stg_runtime.cuda.device import gpu_available

SIM = os.environ.get("NUMBA_ENABLE_CUDASIM") == "1"
GPU = not SIM and gpu_available()
RUN = SIM or GPU
needs_kernels = pytest.mark.skipif(not RUN, reason="no GPU here: these run in the simulator subprocess "
                                                   "(test_under_simulator)")
BIG = 3000 if SIM else 1_000_000  # the largest arrays: a few tiles in the simulator
SMALL = {"_block": 4, "_items": 2}  # tiles of 8 elements: many blocks, deep scan recursion
EXPECTED_PASSED = 37  # the tests this file runs under the simulator (see test_under_simulator)


def _dev(a):
    from numba import cuda
    return cuda.to_device(a)


def _check_scan(counts, **kw):
    d = _dev(counts)
    offsets, total = sort_cuda.exclusive_scan(d, **kw)
    got = offsets.copy_to_host()
    want = np.cumsum(counts, dtype=np.int64)
    assert got.dtype == np.int64 and got.shape == counts.shape
    np.testing.assert_array_equal(got, want - counts.astype(np.int64))
    assert type(total) is int and total == (int(want[-1]) if len(counts) else 0)
    np.testing.assert_array_equal(d.copy_to_host(), counts)  # the input is untouched


def _check_sort(keys, key_bits, with_values=True, **kw):
    values = np.arange(len(keys), dtype=np.int32)  # the original indices: ties must keep their order
    kd = _dev(keys)
    vd = _dev(values) if with_values else None
    got_k, got_v = sort_cuda.radix_sort(kd, vd, key_bits, **kw)
    low = keys & np.int64((1 << key_bits) - 1) if key_bits < 64 else keys
    order = np.argsort(low, kind="stable")
    assert got_k.dtype == np.int64 and got_k.shape == keys.shape
    np.testing.assert_array_equal(got_k.copy_to_host(), keys[order])
    if with_values:
        assert got_v.dtype == np.int32
        np.testing.assert_array_equal(got_v.copy_to_host(), order)
        np.testing.assert_array_equal(vd.copy_to_host(), values)
    else:
        assert got_v is None
    np.testing.assert_array_equal(kd.copy_to_host(), keys)  # the inputs are untouched


@needs_kernels
@pytest.mark.parametrize("dtype", [np.int32, np.int64])
@pytest.mark.parametrize("n", [0, 1, 300, 1024, 5000 if SIM else 3_000_000])
def test_exclusive_scan_matches_cumsum(n, dtype):
    rng = np.random.default_rng(n)
    _check_scan(rng.integers(0, 1000, n).astype(dtype))


@needs_kernels
@pytest.mark.parametrize("n", [0, 1, 7, 8, 9, 700])
def test_exclusive_scan_recursion_small_tiles(n):
    # 700 elements in tiles of 8: 88 tiles, then 11, 2, 1 (four levels); int32 counts near 2^31 whose
    # sums only fit int64
    counts = np.random.default_rng(n).integers(2**31 - 100, 2**31, n).astype(np.int32)
    _check_scan(counts, **SMALL)


@needs_kernels
def test_exclusive_scan_accepts_host_arrays_and_rejects_floats():
    offsets, total = sort_cuda.exclusive_scan(np.array([3, 0, 4], np.int64))
    np.testing.assert_array_equal(offsets.copy_to_host(), [0, 3, 3])
    assert total == 7
    with pytest.raises(TypeError, match="int32 or int64"):
        sort_cuda.exclusive_scan(np.zeros(3, np.float32))


@needs_kernels
@pytest.mark.parametrize("n, key_bits", [
    (0, 8), (1, 8), (2, 8), (255, 8), (256, 8), (257, 6), (1023, 5), (1024, 5), (1025, 8), (BIG, 12),
])
def test_radix_sort_is_stable_argsort(n, key_bits):
    rng = np.random.default_rng(n + key_bits)
    keys = rng.integers(0, 1 << key_bits, n).astype(np.int64)
    keys[: n // 2] = keys[: n // 2] % 7  # many duplicates
    rng.shuffle(keys)
    _check_sort(keys, key_bits)


@needs_kernels
@pytest.mark.parametrize("n, key_bits", [(1, 4), (9, 4), (100, 9), (301, 12)])
def test_radix_sort_small_tiles(n, key_bits):
    # several tiles of 8, an odd and an even number of passes, 16 * tiles histogram entries scanned
    # over several levels
    keys = np.random.default_rng(n).integers(0, 1 << key_bits, n).astype(np.int64) // 3 * 3
    _check_sort(keys, key_bits, **SMALL)


@needs_kernels
@pytest.mark.parametrize("key_bits", [63, 64])
def test_radix_sort_large_keys(key_bits):
    # keys near 2^62 that differ in their low and their high bits: all 16 passes
    rng = np.random.default_rng(key_bits)
    n = 60 if SIM else 200_000
    keys = (2**62 - rng.integers(0, 4, n) * 2**58 - rng.integers(0, 50, n)).astype(np.int64)
    keys[::5] = 2**62 + 2**61 + 17
    keys[1::7] = 0
    _check_sort(keys, key_bits, **({"_block": 8, "_items": 4} if SIM else {}))  # 2 tiles in the simulator


@needs_kernels
def test_radix_sort_default_tiles_many_passes():
    key_bits = 20 if SIM else 64  # every pass of a default block costs about a second in the simulator
    keys = np.random.default_rng(3).integers(0, 2**62, 40 if SIM else 500_000).astype(np.int64)
    keys[::3] = keys[0]
    low_bits = np.array((1 << key_bits) - 1, np.uint64).view(np.int64)  # all 64 bits: -1
    keys[1::3] &= low_bits  # sorted by the low bits only when key_bits < 64
    _check_sort(keys, key_bits, with_values=False)


@needs_kernels
def test_radix_sort_without_values_and_zero_bits():
    keys = np.array([5, 3, 9, 3, 0], np.int64)
    _check_sort(keys, 4, with_values=False)
    _check_sort(keys, 0)  # no passes: a copy
    got, none = sort_cuda.radix_sort(keys, None, 0)
    assert none is None and got.copy_to_host().tolist() == keys.tolist()
    _check_sort(keys[:0], 0)


@needs_kernels
def test_radix_sort_orders_by_the_low_bits_only():
    keys = np.array([0x35, 0x12, 0x25, 0x02, 0x11], np.int64)
    got, values = sort_cuda.radix_sort(keys, np.arange(5, dtype=np.int32), 4)
    assert got.copy_to_host().tolist() == [0x11, 0x12, 0x02, 0x35, 0x25]
    assert values.copy_to_host().tolist() == [4, 1, 3, 0, 2]


@needs_kernels
def test_radix_sort_rejects_bad_arguments():
    with pytest.raises(TypeError, match="int64"):
        sort_cuda.radix_sort(np.zeros(4, np.int32))
    with pytest.raises(ValueError, match="key_bits"):
        sort_cuda.radix_sort(np.zeros(4, np.int64), None, 65)
    with pytest.raises(ValueError, match="elements"):
        sort_cuda.radix_sort(np.zeros(4, np.int64), np.zeros(3, np.int32))
    with pytest.raises(ValueError, match="1-D"):
        sort_cuda.radix_sort(np.zeros((2, 2), np.int64))
    with pytest.raises(ValueError, match="block"):
        sort_cuda.exclusive_scan(np.zeros(4, np.int64), _block=6)


def test_under_simulator(run_under_simulator):
    if RUN:
        pytest.skip("the kernels run directly in this process")
    run_under_simulator(__file__, passed=EXPECTED_PASSED)
