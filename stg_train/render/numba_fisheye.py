"""The fisheye EWA projection of the CPU training splatter, forward and backward, in numba (no torch).

    forward(means, quats, scales, opacities, cam, means2d, conic, depth, radius, valid)
    backward(means, quats, scales, cam, valid, g_means2d, g_conic, g_depth, g_means, g_quats, g_scales)

The same arguments as stg_train.render.numba_projection's pinhole pair, and the rules of
formats/stg-v1.md sections 1 and 3 as stg_train.render.torch_splat's `_fisheye` states them (its
outputs and their gradients, value for value): camera-space p = R w + t; seen = z > NEAR and
theta = atan2(r, z) < max_angle (r = |(x, y)|); the 2D mean (fx x s + cx, fy y s + cy) with
s = theta_d / r; the 2D covariance T T^T + 0.3 I with T = J R Rq S, J the exact Jacobian of that map
(no clamp); on the axis (r <= 1e-7 z) the limits s = 1/z, a = (2 k1 - 2/3) / z^3 with theta taken as
0 (no gradient through theta there); a Gaussian that is not seen has the mean (cx, cy) and no
gradient but its depth's. cam: stg_runtime.projection.camera_params(camera) (k1..k4 at 24..27,
max_angle at 28). Arithmetic in float64, outputs in the output arrays' dtype.

numba caches these kernels (cache=True) and checks only this file for changes: after editing the
helpers imported from numba_projection, delete stg_train/render/__pycache__/*.nbi (or touch this file).
"""
from __future__ import annotations

import math

import numba
import numpy as np

from stg_runtime.spec import BLUR, MIN_ALPHA, NEAR

from .numba_projection import axes, axes_backward, camera_point, conic_backward, store_conic


@numba.njit(cache=True)
def _map(cam, x, y, z):
    """The fisheye map at camera-space (x, y, z), z > 0: (off the axis, r2, r, theta, slope, rho2,
    s = theta_d / r, a = (ds/dr) / r), on the axis with their limits (theta = 0, slope = 1)."""
    k1, k2, k3, k4 = cam[24], cam[25], cam[26], cam[27]
    r2 = x * x + y * y
    rho2 = r2 + z * z
    if r2 > (1e-7 * z) ** 2:
        r = math.sqrt(r2)
        theta = math.atan2(r, z)
        t2 = theta * theta
        theta_d = theta * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
        slope = 1.0 + t2 * (3.0 * k1 + t2 * (5.0 * k2 + t2 * (7.0 * k3 + t2 * 9.0 * k4)))
        s = theta_d / r
        return True, r2, r, theta, slope, rho2, s, (slope * z / rho2 - s) / r2
    return False, r2, 0.0, 0.0, 1.0, rho2, 1.0 / z, (2.0 * k1 - 2.0 / 3.0) / (z * z * z)


@numba.njit(cache=True)
def _seen(cam, x, y, z):
    """In front of the near plane and less than max_angle off the axis."""
    return z > NEAR and math.atan2(math.sqrt(x * x + y * y), z) < cam[28]


@numba.njit(cache=True)
def _covariance(cam, quats, scales, i, x, y, z):
    """Gaussian i seen from camera-space mean (x, y, z): (its axes M, unit quaternion and norm (axes),
    the fisheye map (_map), J (6 entries, row-major 2 x 3), T = J M (6), the covariance a, b, c with
    the blur)."""
    m, q, norm = axes(cam, quats, scales, i)
    fmap = _map(cam, x, y, z)
    slope, rho2, s, a_r = fmap[4], fmap[5], fmap[6], fmap[7]
    fx, fy = cam[12], cam[13]
    j = (fx * (s + x * x * a_r), fx * x * y * a_r, -fx * x * slope / rho2,
         fy * x * y * a_r, fy * (s + y * y * a_r), -fy * y * slope / rho2)
    t = (j[0] * m[0] + j[1] * m[3] + j[2] * m[6], j[0] * m[1] + j[1] * m[4] + j[2] * m[7],
         j[0] * m[2] + j[1] * m[5] + j[2] * m[8],
         j[3] * m[0] + j[4] * m[3] + j[5] * m[6], j[3] * m[1] + j[4] * m[4] + j[5] * m[7],
         j[3] * m[2] + j[4] * m[5] + j[5] * m[8])
    a = t[0] * t[0] + t[1] * t[1] + t[2] * t[2] + BLUR
    b = t[0] * t[3] + t[1] * t[4] + t[2] * t[5]
    c = t[3] * t[3] + t[4] * t[4] + t[5] * t[5] + BLUR
    return m, q, norm, fmap, j, t, a, b, c


@numba.njit(parallel=True, cache=True)
def forward(means, quats, scales, opacities, cam, means2d, conic, depth, radius, valid):
    """Fill means2d (M, 2), conic (M, 3), depth (M,), radius (M,) int64 and valid (M,) bool."""
    for i in numba.prange(means.shape[0]):
        x, y, z = camera_point(cam, means, i)
        depth[i] = z
        means2d[i, 0] = cam[14]
        means2d[i, 1] = cam[15]
        conic[i, 0] = conic[i, 1] = conic[i, 2] = 0.0
        radius[i] = 0
        valid[i] = False
        if not _seen(cam, x, y, z):
            continue
        _, _, _, fmap, _, _, a, b, c = _covariance(cam, quats, scales, i, x, y, z)
        means2d[i, 0] = cam[12] * x * fmap[6] + cam[14]
        means2d[i, 1] = cam[13] * y * fmap[6] + cam[15]
        if np.float64(opacities[i]) >= MIN_ALPHA:
            store_conic(a, b, c, i, conic, radius, valid)


@numba.njit(parallel=True, cache=True)
def backward(means, quats, scales, cam, valid, g_means2d, g_conic, g_depth, g_means, g_quats, g_scales):
    """The vector-Jacobian product of `forward`: from dL/d means2d (M, 2), dL/d conic (M, 3) and
    dL/d depth (M,), fill dL/d means (M, 3), dL/d quats (M, 4) and dL/d scales (M, 3)."""
    for i in numba.prange(means.shape[0]):
        x, y, z = camera_point(cam, means, i)
        g_quats[i, 0] = g_quats[i, 1] = g_quats[i, 2] = g_quats[i, 3] = 0.0
        g_scales[i, 0] = g_scales[i, 1] = g_scales[i, 2] = 0.0
        gx, gy, gz = 0.0, 0.0, np.float64(g_depth[i])
        if _seen(cam, x, y, z):
            m, q, norm, fmap, j, t, a, b, c = _covariance(cam, quats, scales, i, x, y, z)
            gj = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
            if valid[i]:
                gt = conic_backward(g_conic, i, t, a, b, c)
                # T = J M: dL/dJ = dL/dT M^T, dL/dM = J^T dL/dT.
                gj = (gt[0] * m[0] + gt[1] * m[1] + gt[2] * m[2], gt[0] * m[3] + gt[1] * m[4] + gt[2] * m[5],
                      gt[0] * m[6] + gt[1] * m[7] + gt[2] * m[8], gt[3] * m[0] + gt[4] * m[1] + gt[5] * m[2],
                      gt[3] * m[3] + gt[4] * m[4] + gt[5] * m[5], gt[3] * m[6] + gt[4] * m[7] + gt[5] * m[8])
                gm = (j[0] * gt[0] + j[3] * gt[3], j[0] * gt[1] + j[3] * gt[4], j[0] * gt[2] + j[3] * gt[5],
                      j[1] * gt[0] + j[4] * gt[3], j[1] * gt[1] + j[4] * gt[4], j[1] * gt[2] + j[4] * gt[5],
                      j[2] * gt[0] + j[5] * gt[3], j[2] * gt[1] + j[5] * gt[4], j[2] * gt[2] + j[5] * gt[5])
                axes_backward(cam, scales, i, q, norm, gm, g_quats, g_scales)
            gx, gy, gz = _map_backward(cam, x, y, z, fmap, np.float64(g_means2d[i, 0]),
                                       np.float64(g_means2d[i, 1]), gj, gz)
        for k in range(3):  # p = R w + t
            g_means[i, k] = cam[k] * gx + cam[3 + k] * gy + cam[6 + k] * gz


@numba.njit(cache=True)
def _map_backward(cam, x, y, z, fmap, gu, gv, gj, gz):
    """dL/d(x, y, z) of the mean (u, v) and of J (gj, 6 entries) through the fisheye map (_map), plus
    gz already gathered (the depth's)."""
    fx, fy = cam[12], cam[13]
    k1, k2, k3, k4 = cam[24], cam[25], cam[26], cam[27]
    off_axis, r2, r, theta, slope, rho2, s, a_r = fmap
    # u = fx x s + cx, v = fy y s + cy; J = [[fx (s + x^2 a), fx x y a, -fx x slope / rho2],
    #                                         [fy x y a, fy (s + y^2 a), -fy y slope / rho2]].
    g_s = fx * gj[0] + fy * gj[4] + fx * x * gu + fy * y * gv
    g_a = fx * x * x * gj[0] + (fx * gj[1] + fy * gj[3]) * x * y + fy * y * y * gj[4]
    g_slope = -(fx * x * gj[2] + fy * y * gj[5]) / rho2
    g_rho2 = (fx * x * gj[2] + fy * y * gj[5]) * slope / (rho2 * rho2)
    gx = fx * 2.0 * x * a_r * gj[0] + (fx * gj[1] + fy * gj[3]) * y * a_r - fx * slope / rho2 * gj[2] + fx * s * gu
    gy = (fx * gj[1] + fy * gj[3]) * x * a_r + fy * 2.0 * y * a_r * gj[4] - fy * slope / rho2 * gj[5] + fy * s * gv
    g_r2 = 0.0
    if off_axis:
        # a = (slope z / rho2 - s) / r2
        g_slope += g_a * z / (rho2 * r2)
        gz += g_a * slope / (rho2 * r2)
        g_rho2 -= g_a * slope * z / (rho2 * rho2 * r2)
        g_s -= g_a / r2
        g_r2 -= g_a * a_r / r2
        # s = theta_d / r; theta_d' = slope; slope' = 2 theta (3 k1 + t2 (10 k2 + t2 (21 k3 + 36 k4 t2)))
        t2 = theta * theta
        g_theta = g_s / r * slope + g_slope * 2.0 * theta * (3.0 * k1 + t2 * (10.0 * k2 + t2 * (21.0 * k3 + t2 * 36.0 * k4)))
        g_r = -g_s * s / r
        # theta = atan2(r, z)
        g_r += g_theta * z / rho2
        gz -= g_theta * r / rho2
        g_r2 += g_r / (2.0 * r)
    else:
        # s = 1 / z, a = (2 k1 - 2/3) / z^3
        gz -= g_s / (z * z) + 3.0 * g_a * a_r / z
    # rho2 = r2 + z^2, r2 = x^2 + y^2
    g_r2 += g_rho2
    gz += 2.0 * z * g_rho2
    return gx + 2.0 * x * g_r2, gy + 2.0 * y * g_r2, gz
