"""Scalar helpers for the numba.cuda kernels.

dmin/dmax replace the builtins min/max of two numbers inside kernels, with Python's semantics
(dmin(a, b) is b only if b < a): numba 0.66 to 0.68's own CUDA target fails to compile the two-argument
builtins (numba issue #10753; numba-cuda is not affected). They are device functions, inlined.
"""
from __future__ import annotations

from numba import cuda


@cuda.jit(device=True, inline=True)
def dmin(a, b):
    return b if b < a else a


@cuda.jit(device=True, inline=True)
def dmax(a, b):
    return b if b > a else a
