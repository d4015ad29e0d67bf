"""Scalar helpers for the numba.cuda kernels.

dmin/dmax replace the builtins min/max of two numbers inside kernels, with Python's semantics
(dmin(a, b) is b only if b < a): some numba versions' own CUDA target cannot compile the two-argument
builtins (docs/gpu.md names them). They are device functions, inlined.
"""
from __future__ import annotations

from numba import cuda


@cuda.jit(device=True, inline=True)
def dmin(a, b):
    return b if b < a else a


@cuda.jit(device=True, inline=True)
def dmax(a, b):
    return b if b > a else a
