"""The adaptive binary range coder of format 1.5's `acB` encodings (formats/stg-v1.md, "Arithmetic-
coded fixed point (1.5)"); numpy + numba.

    encode(symbols, bits) -> bytes          symbols (C, N) integers in [0, 2^bits), one row a channel
    decode(data, channels, count, bits) -> (C, N) uint16; ValueError for a stream that is not one

Each channel's symbols are coded most significant bit first down a binary tree of `bits` levels;
every tree node holds an 11-bit probability of a 0, starting at one half for each channel and moving
1/32 of the way towards each bit it codes. One stream holds every channel in order. The decoder
reads exactly the bytes the encoder wrote, so a stream that ends early or has bytes left over is
refused, as is one whose first byte is not 0 (an encoder's first byte always is).
"""
from __future__ import annotations

import numba
import numpy as np

PROB_BITS = 11  # probabilities of a 0 in units of 2^-11
ADAPT_SHIFT = 5  # a probability moves 1/32 of the way towards each coded bit
TOP = 1 << 24  # the range is renormalised (a byte shifted in or out) while below this
MAX_BITS = 16


@numba.njit(cache=True)
def _encode(symbols: np.ndarray, bits: int, out: np.ndarray) -> int:
    """Code symbols (C, N) int64 into out (uint8, large enough); returns the bytes written."""
    one = 1 << PROB_BITS
    low, rng, cache, pending, n = 0, 0xFFFFFFFF, 0, 1, 0
    for c in range(symbols.shape[0]):
        probs = np.full(1 << bits, one >> 1, np.int64)
        for i in range(symbols.shape[1]):
            s, node = symbols[c, i], 1
            for b in range(bits - 1, -1, -1):
                bit = (s >> b) & 1
                p = probs[node]
                bound = (rng >> PROB_BITS) * p
                if bit == 0:
                    rng = bound
                    probs[node] = p + ((one - p) >> ADAPT_SHIFT)
                else:
                    low += bound
                    rng -= bound
                    probs[node] = p - (p >> ADAPT_SHIFT)
                node = 2 * node + bit
                while rng < TOP:
                    rng <<= 8
                    low, cache, pending, n = _shift_low(low, cache, pending, out, n)
    for _ in range(5):  # flush: the last four bytes of low and the byte still held
        low, cache, pending, n = _shift_low(low, cache, pending, out, n)
    return n


@numba.njit(cache=True, inline="always")
def _shift_low(low: int, cache: int, pending: int, out: np.ndarray, n: int):
    """Move low's top byte out: held back while it is 0xFF (a carry may still reach it), written
    with the carry (and the bytes held before it) once it no longer can."""
    if (low & 0xFFFFFFFF) < 0xFF000000 or low >= (1 << 32):
        carry = low >> 32
        byte = cache
        while pending > 0:
            out[n] = (byte + carry) & 0xFF
            n += 1
            byte = 0xFF
            pending -= 1
        cache = (low >> 24) & 0xFF
    pending += 1
    low = (low & 0x00FFFFFF) << 8
    return low, cache, pending, n


@numba.njit(cache=True)
def _decode(data: np.ndarray, channels: int, count: int, bits: int, out: np.ndarray) -> int:
    """Decode channels x count symbols of `bits` bits into out (C, N); returns the bytes read, or -1
    if the stream ends before the symbols do."""
    one = 1 << PROB_BITS
    if data.size < 5:
        return -1
    rng, code, at = 0xFFFFFFFF, 0, 5
    for k in range(1, 5):
        code = (code << 8) | data[k]
    for c in range(channels):
        probs = np.full(1 << bits, one >> 1, np.int64)
        for i in range(count):
            node = 1
            for _ in range(bits):
                p = probs[node]
                bound = (rng >> PROB_BITS) * p
                if code < bound:
                    rng = bound
                    probs[node] = p + ((one - p) >> ADAPT_SHIFT)
                    node = 2 * node
                else:
                    code -= bound
                    rng -= bound
                    probs[node] = p - (p >> ADAPT_SHIFT)
                    node = 2 * node + 1
                while rng < TOP:
                    if at >= data.size:
                        return -1
                    rng <<= 8
                    code = ((code << 8) | data[at]) & 0xFFFFFFFF
                    at += 1
            out[c, i] = node - (1 << bits)
    return at


def _check_bits(bits: int) -> None:
    if not 1 <= bits <= MAX_BITS:
        raise ValueError(f"bits must be 1 to {MAX_BITS}, got {bits}")


def encode(symbols, bits: int) -> bytes:
    """The coded bytes of `symbols` (C, N) integers in [0, 2^bits) (channel c's row coded after
    channel c-1's)."""
    _check_bits(bits)
    s = np.ascontiguousarray(symbols, dtype=np.int64)
    if s.ndim != 2:
        raise ValueError(f"symbols must be (channels, count), got shape {s.shape}")
    if s.size and (s.min() < 0 or s.max() >= 1 << bits):
        raise ValueError(f"symbols must lie in [0, {1 << bits})")
    # a coded bit costs at most -log2(31 / 2048) ~ 6.05 bits of output (probabilities stay in
    # [31, 2017] / 2048): under a byte per 8 / 7 bits, and 16 bytes for the start and the flush
    out = np.empty(s.size * bits * 7 // 8 + 16, np.uint8)
    n = _encode(s, bits, out)
    return out[:n].tobytes()


def decode(data, channels: int, count: int, bits: int) -> np.ndarray:
    """(channels, count) uint16 symbols of the coded `data` (bytes); ValueError when the data is not
    the stream of exactly that many symbols (first byte not 0, ends early, bytes left over)."""
    _check_bits(bits)
    buf = np.frombuffer(bytes(data), np.uint8)
    if buf.size == 0 or buf[0] != 0:
        raise ValueError("arithmetic-coded data must start with a 0 byte")
    out = np.empty((channels, count), np.uint16)
    used = _decode(buf, int(channels), int(count), int(bits), out)
    if used < 0:
        raise ValueError(f"arithmetic-coded data ends before its {channels * count} values")
    if used != buf.size:
        raise ValueError(f"arithmetic-coded data has {buf.size - used} bytes after its {channels * count} values")
    return out
