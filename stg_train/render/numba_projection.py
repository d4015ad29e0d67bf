"""The pinhole EWA projection of the CPU training splatter, forward and backward, in numba (no torch
here), and the parts that stg_train.render.numba_fisheye shares (camera_point, axes, store_conic,
conic_backward, axes_backward).

    forward(means, quats, scales, opacities, cam, means2d, conic, depth, radius, valid)
    backward(means, quats, scales, cam, valid, g_means2d, g_conic, g_depth, g_means, g_quats, g_scales)

The rules of formats/stg-v1.md, section 3, as stg_train.render.torch_splat.project states them (its
outputs and their gradients, value for value): camera-space p = R w + t; the 2D mean (fx x/z + cx,
fy y/z + cy) (for z <= NEAR, z taken as 1: culled, but finite); the 2D covariance T T^T + 0.3 I with
T = J R Rq S, J the EWA Jacobian with x/z and y/z clamped (no gradient through a clamped value);
the conic [A, B, C] = [c, -b, a] / det of the covariance [[a, b], [b, c]]; the 3-sigma radius;
valid = in front of the near plane, det > 0 and opacity >= 1/255 (no gradient through the conic
otherwise). cam: stg_runtime.projection.camera_params(camera). Arithmetic in float64, outputs in the
output arrays' dtype. One Gaussian per iteration, in parallel.
"""
from __future__ import annotations

import math

import numba
import numpy as np

from stg_runtime.spec import BLUR, MIN_ALPHA, NEAR



@numba.njit(cache=True)
def _rotation(qw, qx, qy, qz):
    """The rotation matrix of the quaternion (w, x, y, z), assumed unit, as 9 row-major entries."""
    return (1.0 - 2.0 * (qy * qy + qz * qz), 2.0 * (qx * qy - qw * qz), 2.0 * (qx * qz + qw * qy),
            2.0 * (qx * qy + qw * qz), 1.0 - 2.0 * (qx * qx + qz * qz), 2.0 * (qy * qz - qw * qx),
            2.0 * (qx * qz - qw * qy), 2.0 * (qy * qz + qw * qx), 1.0 - 2.0 * (qx * qx + qy * qy))


@numba.njit(inline="always")
def _rc(cam, r, row, col):
    """(R Rq)[row, col]: the camera rotation R (cam[0:9]) times the Gaussian's rotation r (9 entries)."""
    return cam[row * 3] * r[col] + cam[row * 3 + 1] * r[3 + col] + cam[row * 3 + 2] * r[6 + col]


@numba.njit(cache=True)
def axes(cam, quats, scales, i):
    """(M as 9 row-major entries: the Gaussian's scaled axes in camera space, M = R Rq S; the unit
    quaternion (4); its norm before normalising)."""
    qw, qx, qy, qz = np.float64(quats[i, 0]), np.float64(quats[i, 1]), np.float64(quats[i, 2]), np.float64(quats[i, 3])
    norm = max(math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz), 1e-30)
    qw, qx, qy, qz = qw / norm, qx / norm, qy / norm, qz / norm
    r = _rotation(qw, qx, qy, qz)
    s0, s1, s2 = np.float64(scales[i, 0]), np.float64(scales[i, 1]), np.float64(scales[i, 2])
    m = (_rc(cam, r, 0, 0) * s0, _rc(cam, r, 0, 1) * s1, _rc(cam, r, 0, 2) * s2,
         _rc(cam, r, 1, 0) * s0, _rc(cam, r, 1, 1) * s1, _rc(cam, r, 1, 2) * s2,
         _rc(cam, r, 2, 0) * s0, _rc(cam, r, 2, 1) * s1, _rc(cam, r, 2, 2) * s2)
    return m, (qw, qx, qy, qz), norm


@numba.njit(cache=True)
def _jacobian(cam, x, y, z):
    """The EWA Jacobian's non-zero entries (j00, j02, j11, j12), the clamped x/z and y/z, and whether each
    was inside its range (a gradient flows through it)."""
    xz, yz = x / z, y / z
    x_free = cam[19] <= xz <= cam[20]
    y_free = cam[21] <= yz <= cam[22]
    xz = min(max(xz, cam[19]), cam[20])
    yz = min(max(yz, cam[21]), cam[22])
    return cam[12] / z, -cam[12] * xz / z, cam[13] / z, -cam[13] * yz / z, xz, yz, x_free, y_free


@numba.njit(cache=True)
def _covariance(cam, quats, scales, i, x, y, z):
    """Gaussian i seen from camera-space mean (x, y, z): (its axes M (axes), the unit quaternion and
    its norm, the Jacobian (_jacobian), T = J M as two rows of 3, and the 2D covariance a, b, c with the
    blur)."""
    m, q, norm = axes(cam, quats, scales, i)
    jac = _jacobian(cam, x, y, z)
    j00, j02, j11, j12 = jac[0], jac[1], jac[2], jac[3]
    t = (j00 * m[0] + j02 * m[6], j00 * m[1] + j02 * m[7], j00 * m[2] + j02 * m[8],
         j11 * m[3] + j12 * m[6], j11 * m[4] + j12 * m[7], j11 * m[5] + j12 * m[8])
    a = t[0] * t[0] + t[1] * t[1] + t[2] * t[2] + BLUR
    b = t[0] * t[3] + t[1] * t[4] + t[2] * t[5]
    c = t[3] * t[3] + t[4] * t[4] + t[5] * t[5] + BLUR
    return m, q, norm, jac, t, a, b, c


@numba.njit(inline="always")
def camera_point(cam, means, i):
    """Gaussian i's mean (means (M, 3), world) in camera space, (x, y, z) float64: R w + t (cam as
    stg_runtime.projection.camera_params)."""
    wx, wy, wz = np.float64(means[i, 0]), np.float64(means[i, 1]), np.float64(means[i, 2])
    return (cam[0] * wx + cam[1] * wy + cam[2] * wz + cam[9], cam[3] * wx + cam[4] * wy + cam[5] * wz + cam[10],
            cam[6] * wx + cam[7] * wy + cam[8] * wz + cam[11])


@numba.njit(cache=True)
def store_conic(a, b, c, i, conic, radius, valid):
    """For the 2D covariance [[a, b], [b, c]] (blur included) of Gaussian i: when its determinant is
    positive, valid[i] = True, conic[i] = its inverse [A, B, C] and radius[i] = the spec's 3-sigma radius
    (pixels); else nothing changes."""
    det = a * c - b * b
    if not det > 0.0:
        return
    valid[i] = True
    conic[i, 0] = c / det
    conic[i, 1] = -b / det
    conic[i, 2] = a / det
    mid = 0.5 * (a + c)
    lam = mid + math.sqrt(max(mid * mid - det, 0.1))
    radius[i] = int(math.ceil(3.0 * math.sqrt(max(lam, 0.0))))


@numba.njit(parallel=True, cache=True)
def forward(means, quats, scales, opacities, cam, means2d, conic, depth, radius, valid):
    """Fill means2d (M, 2), conic (M, 3), depth (M,), radius (M,) int64 and valid (M,) bool."""
    for i in numba.prange(means.shape[0]):
        x, y, z = camera_point(cam, means, i)
        depth[i] = z
        in_front = z > NEAR
        zs = z if in_front else 1.0
        means2d[i, 0] = cam[12] * x / zs + cam[14]
        means2d[i, 1] = cam[13] * y / zs + cam[15]
        conic[i, 0] = conic[i, 1] = conic[i, 2] = 0.0
        radius[i] = 0
        valid[i] = False
        if not in_front or not np.float64(opacities[i]) >= MIN_ALPHA:
            continue
        _, _, _, _, _, a, b, c = _covariance(cam, quats, scales, i, x, y, z)
        store_conic(a, b, c, i, conic, radius, valid)


@numba.njit(parallel=True, cache=True)
def backward(means, quats, scales, cam, valid, g_means2d, g_conic, g_depth, g_means, g_quats, g_scales):
    """The vector-Jacobian product of `forward`: from dL/d means2d (M, 2), dL/d conic (M, 3) and
    dL/d depth (M,), fill dL/d means (M, 3), dL/d quats (M, 4) and dL/d scales (M, 3)."""
    fx, fy = cam[12], cam[13]
    for i in numba.prange(means.shape[0]):
        x, y, z = camera_point(cam, means, i)
        gu, gv = np.float64(g_means2d[i, 0]), np.float64(g_means2d[i, 1])
        gz = np.float64(g_depth[i])
        g_quats[i, 0] = g_quats[i, 1] = g_quats[i, 2] = g_quats[i, 3] = 0.0
        g_scales[i, 0] = g_scales[i, 1] = g_scales[i, 2] = 0.0
        if not z > NEAR:  # the 2D mean with z taken as 1
            gx, gy = gu * fx, gv * fy
        else:
            gx, gy = gu * fx / z, gv * fy / z
            gz -= (gu * fx * x + gv * fy * y) / (z * z)
        if valid[i]:
            gx, gy, gz = _covariance_backward(cam, quats, scales, g_conic, i, x, y, z, gx, gy, gz, g_quats, g_scales)
        for k in range(3):  # p = R w + t
            g_means[i, k] = cam[k] * gx + cam[3 + k] * gy + cam[6 + k] * gz


@numba.njit(inline="always")
def _rtg(cam, gm, row, col):
    """(R^T G)[row, col] for the camera rotation R (cam[0:9]) and G (9 entries, row-major)."""
    return cam[row] * gm[col] + cam[3 + row] * gm[3 + col] + cam[6 + row] * gm[6 + col]


@numba.njit(cache=True)
def _covariance_backward(cam, quats, scales, g_conic, i, x, y, z, gx, gy, gz, g_quats, g_scales):
    """Add the conic's gradient to (gx, gy, gz) (camera space) and write dL/d quats and dL/d scales of
    Gaussian i. Returns the new (gx, gy, gz)."""
    fx, fy = cam[12], cam[13]
    m, q, norm, jac, t, a, b, c = _covariance(cam, quats, scales, i, x, y, z)
    j00, j02, j11, j12, xz, yz, x_free, y_free = jac
    gt = conic_backward(g_conic, i, t, a, b, c)
    # T = J M: dL/dJ = dL/dT M^T (its non-zero entries), dL/dM = J^T dL/dT.
    g00 = gt[0] * m[0] + gt[1] * m[1] + gt[2] * m[2]
    g02 = gt[0] * m[6] + gt[1] * m[7] + gt[2] * m[8]
    g11 = gt[3] * m[3] + gt[4] * m[4] + gt[5] * m[5]
    g12 = gt[3] * m[6] + gt[4] * m[7] + gt[5] * m[8]
    gm = (j00 * gt[0], j00 * gt[1], j00 * gt[2], j11 * gt[3], j11 * gt[4], j11 * gt[5],
          j02 * gt[0] + j12 * gt[3], j02 * gt[1] + j12 * gt[4], j02 * gt[2] + j12 * gt[5])
    # J's entries in terms of x, y, z: j00 = fx / z, j02 = -fx xz / z (xz = x / z unless clamped).
    gz -= (g00 * fx + g11 * fy) / (z * z)
    if x_free:
        gx -= g02 * fx / (z * z)
        gz += g02 * 2.0 * fx * x / (z * z * z)
    else:
        gz += g02 * fx * xz / (z * z)
    if y_free:
        gy -= g12 * fy / (z * z)
        gz += g12 * 2.0 * fy * y / (z * z * z)
    else:
        gz += g12 * fy * yz / (z * z)
    axes_backward(cam, scales, i, q, norm, gm, g_quats, g_scales)
    return gx, gy, gz


@numba.njit(cache=True)
def conic_backward(g_conic, i, t, a, b, c):
    """dL/dT (6 entries, row-major 2 x 3) from dL/d conic of Gaussian i, where the covariance
    [[a, b], [b, c]] = T T^T + blur and the conic is its inverse [c, -b, a] / det."""
    det = a * c - b * b
    gA, gB, gC = np.float64(g_conic[i, 0]), np.float64(g_conic[i, 1]), np.float64(g_conic[i, 2])
    d2 = det * det
    ga = (-gA * c * c + gB * b * c - gC * b * b) / d2
    gb = (2.0 * gA * b * c - gB * (a * c + b * b) + 2.0 * gC * a * b) / d2
    gc = (-gA * b * b + gB * a * b - gC * a * a) / d2
    return (2.0 * ga * t[0] + gb * t[3], 2.0 * ga * t[1] + gb * t[4], 2.0 * ga * t[2] + gb * t[5],  # cov = T T^T
            gb * t[0] + 2.0 * gc * t[3], gb * t[1] + 2.0 * gc * t[4], gb * t[2] + 2.0 * gc * t[5])


@numba.njit(cache=True)
def axes_backward(cam, scales, i, q, norm, gm, g_quats, g_scales):
    """Write dL/d quats and dL/d scales of Gaussian i from dL/dM (gm, 9 entries row-major) of its axes
    M = R Rq S (axes; q its unit quaternion, norm the quaternion's length before normalising)."""
    # M = R Rq S: dL/d(Rq S) = R^T dL/dM, then split into Rq and S.
    qw, qx, qy, qz = q
    r = _rotation(qw, qx, qy, qz)
    s0, s1, s2 = np.float64(scales[i, 0]), np.float64(scales[i, 1]), np.float64(scales[i, 2])
    gr = (_rtg(cam, gm, 0, 0) * s0, _rtg(cam, gm, 0, 1) * s1, _rtg(cam, gm, 0, 2) * s2,
          _rtg(cam, gm, 1, 0) * s0, _rtg(cam, gm, 1, 1) * s1, _rtg(cam, gm, 1, 2) * s2,
          _rtg(cam, gm, 2, 0) * s0, _rtg(cam, gm, 2, 1) * s1, _rtg(cam, gm, 2, 2) * s2)
    for col in range(3):  # S's gradient: (R^T dL/dM)[:, col] . Rq[:, col]
        g_scales[i, col] = (_rtg(cam, gm, 0, col) * r[col] + _rtg(cam, gm, 1, col) * r[3 + col]
                            + _rtg(cam, gm, 2, col) * r[6 + col])
    gw = 2.0 * (-qz * gr[1] + qy * gr[2] + qz * gr[3] - qx * gr[5] - qy * gr[6] + qx * gr[7])
    gqx = 2.0 * (qy * gr[1] + qz * gr[2] + qy * gr[3] - 2.0 * qx * gr[4] - qw * gr[5] + qz * gr[6]
                 + qw * gr[7] - 2.0 * qx * gr[8])
    gqy = 2.0 * (-2.0 * qy * gr[0] + qx * gr[1] + qw * gr[2] + qx * gr[3] + qz * gr[5] - qw * gr[6]
                 + qz * gr[7] - 2.0 * qy * gr[8])
    gqz = 2.0 * (-2.0 * qz * gr[0] - qw * gr[1] + qx * gr[2] + qw * gr[3] - 2.0 * qz * gr[4] + qy * gr[5]
                 + qx * gr[6] + qy * gr[7])
    dot = qw * gw + qx * gqx + qy * gqy + qz * gqz  # through q / |q|
    g_quats[i, 0] = (gw - qw * dot) / norm
    g_quats[i, 1] = (gqx - qx * dot) / norm
    g_quats[i, 2] = (gqy - qy * dot) / norm
    g_quats[i, 3] = (gqz - qz * dot) / norm
