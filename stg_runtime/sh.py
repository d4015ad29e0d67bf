"""Spherical-harmonics colour ("sh" models, formats/stg-v1.md section 2), as 3D Gaussian Splatting does it.

Each Gaussian holds K = (d + 1)^2 real SH coefficients per colour channel (degree d in 0..3), stored
coefficient-major: features (N, 3 K) with features[:, 3 k + c] = coefficient k of channel c (r, g, b).
Per Gaussian and view, with `dir` the unit vector from the camera centre to the Gaussian's mean:
rgb = max(sum_k Y_k(dir) coefficient_k + 0.5, 0), Y_k the real SH basis with 3DGS's constants and signs.
"""
from __future__ import annotations

import math

import numba
import numpy as np

from .model import sh_degree_of
from .spec import SH_C0 as C0
from .spec import SH_C1 as C1
from .spec import SH_C2 as C2
from .spec import SH_C3 as C3


def sh_colour_at(coeffs, means, cx, cy, cz, i, out):
    """out[i] = Gaussian i's rgb seen from the camera centre (cx, cy, cz) (see sh_colours), in float64.

    Plain Python that numba compiles for each target: _sh_colours here, and stg_runtime.cuda.decoder's
    kernel (so it calls no helper functions, nor the two-argument builtin max: see docs/gpu.md)."""
    k_count = coeffs.shape[1] // 3
    dx = np.float64(means[i, 0]) - cx
    dy = np.float64(means[i, 1]) - cy
    dz = np.float64(means[i, 2]) - cz
    norm = math.sqrt(dx * dx + dy * dy + dz * dz)
    if norm > 0.0:
        dx, dy, dz = dx / norm, dy / norm, dz / norm
    x, y, z = dx, dy, dz
    r = C0 * coeffs[i, 0]
    g = C0 * coeffs[i, 1]
    bl = C0 * coeffs[i, 2]
    if k_count > 1:
        xx, yy, zz = x * x, y * y, z * z
        b1 = -C1 * y
        b2 = C1 * z
        b3 = -C1 * x
        r += b1 * coeffs[i, 3] + b2 * coeffs[i, 6] + b3 * coeffs[i, 9]
        g += b1 * coeffs[i, 4] + b2 * coeffs[i, 7] + b3 * coeffs[i, 10]
        bl += b1 * coeffs[i, 5] + b2 * coeffs[i, 8] + b3 * coeffs[i, 11]
        if k_count > 4:
            b4 = C2[0] * x * y
            b5 = C2[1] * y * z
            b6 = C2[2] * (2.0 * zz - xx - yy)
            b7 = C2[3] * x * z
            b8 = C2[4] * (xx - yy)
            r += b4 * coeffs[i, 12] + b5 * coeffs[i, 15] + b6 * coeffs[i, 18] + b7 * coeffs[i, 21] + b8 * coeffs[i, 24]
            g += b4 * coeffs[i, 13] + b5 * coeffs[i, 16] + b6 * coeffs[i, 19] + b7 * coeffs[i, 22] + b8 * coeffs[i, 25]
            bl += b4 * coeffs[i, 14] + b5 * coeffs[i, 17] + b6 * coeffs[i, 20] + b7 * coeffs[i, 23] + b8 * coeffs[i, 26]
            if k_count > 9:
                b9 = C3[0] * y * (3.0 * xx - yy)
                b10 = C3[1] * x * y * z
                b11 = C3[2] * y * (4.0 * zz - xx - yy)
                b12 = C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy)
                b13 = C3[4] * x * (4.0 * zz - xx - yy)
                b14 = C3[5] * z * (xx - yy)
                b15 = C3[6] * x * (xx - 3.0 * yy)
                r += (b9 * coeffs[i, 27] + b10 * coeffs[i, 30] + b11 * coeffs[i, 33] + b12 * coeffs[i, 36]
                      + b13 * coeffs[i, 39] + b14 * coeffs[i, 42] + b15 * coeffs[i, 45])
                g += (b9 * coeffs[i, 28] + b10 * coeffs[i, 31] + b11 * coeffs[i, 34] + b12 * coeffs[i, 37]
                      + b13 * coeffs[i, 40] + b14 * coeffs[i, 43] + b15 * coeffs[i, 46])
                bl += (b9 * coeffs[i, 29] + b10 * coeffs[i, 32] + b11 * coeffs[i, 35] + b12 * coeffs[i, 38]
                       + b13 * coeffs[i, 41] + b14 * coeffs[i, 44] + b15 * coeffs[i, 47])
    r, g, bl = r + 0.5, g + 0.5, bl + 0.5
    out[i, 0] = r if r > 0.0 else 0.0
    out[i, 1] = g if g > 0.0 else 0.0
    out[i, 2] = bl if bl > 0.0 else 0.0


_sh_colour_at = numba.njit(inline="always")(sh_colour_at)


@numba.njit(parallel=True, cache=True)
def _sh_colours(coeffs, means, center, out):
    for i in numba.prange(coeffs.shape[0]):
        _sh_colour_at(coeffs, means, center[0], center[1], center[2], i, out)


def sh_colours(coeffs: np.ndarray, means: np.ndarray, camera_center) -> np.ndarray:
    """Per-Gaussian rgb seen from `camera_center`.

    coeffs (M, 3 K) float32 SH coefficients (coefficient-major, K = 1, 4, 9 or 16); means (M, 3) world
    positions; camera_center (3,) world position. Returns (M, 3) float32 max(SH(dir) + 0.5, 0), dir the
    unit vector from the camera centre to the mean (the zero vector when they coincide).
    """
    coeffs = np.ascontiguousarray(coeffs, dtype=np.float32)
    means = np.ascontiguousarray(means, dtype=np.float32)
    sh_degree_of(coeffs.shape[1])
    if means.shape != (coeffs.shape[0], 3):
        raise ValueError(f"means must be ({coeffs.shape[0]}, 3), got {means.shape}")
    out = np.empty((coeffs.shape[0], 3), np.float32)
    _sh_colours(coeffs, means, np.asarray(camera_center, dtype=np.float64).reshape(3), out)
    return out
