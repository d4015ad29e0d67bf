"""One Gaussian's screen footprint (formats/stg-v1.md, section 3), written once for both splatters.

    camera_params(camera) -> cam          the camera as one tuple of CAMERA_PARAMS float64
    pixel_ray(cam, u, v) -> (dx, dy, dz)  the unit world-space ray through image point (u, v)
    footprint(cam, width, height, means, quats, scales, opacities, i)
        -> (z, u, v, conic_a, conic_b, conic_c, thr, u0, u1, v0, v1)

footprint is plain Python that numba compiles for each target: splat_cpu with numba.njit,
stg_runtime.cuda.splat with cuda.jit(device=True). So it calls no helper functions and no two-argument
min/max (docs/gpu.md says why). For Gaussian i of the arrays (float32:
means (M, 3) world units, quats (M, 4) wxyz, normalised here, zero being the identity, scales (M, 3),
opacities (M,)), in float64, it returns:

- the camera-space depth z (always);
- the 2D mean (u, v) in pixels;
- the conic (power = conic_a dx^2 + conic_b dx dy + conic_c dy^2);
- thr = log(255 o) + 0.01 (alpha >= 1/255 needs power <= log(255 o); 0.01 of margin for rounding);
- the inclusive rectangle of pixel columns u0..u1 and rows v0..v1 (integers) whose centres lie within
  the 3-sigma radius and the ellipse power <= thr, clipped to the image.

A culled Gaussian (z <= NEAR, opacity below 1/255, for a fisheye an angle off the axis at or beyond
the camera's max_angle, a degenerate covariance, or no pixel in its rectangle) has u0 > u1.

splat_cpu caches its compiled kernels (numba's cache=True), and numba checks only the source file of
the cached function: after editing this file, delete stg_runtime/__pycache__/*.nbi (or touch
splat_cpu.py) so that the CPU splatter is compiled again.
"""
from __future__ import annotations

import math

import numpy as np

from .spec import BLUR, JACOBIAN_MARGIN, MIN_ALPHA, NEAR

#: Length of camera_params' tuple: R row-major (0..8), t (9..11), fx, fy, cx, cy (12..15), the camera
#: centre (16..18), the range that x/z and y/z are clamped to in the pinhole EWA Jacobian (19..22), the
#: model (23: 0 pinhole, 1 fisheye), the fisheye's k1..k4 (24..27) and its max_angle (28, radians).
CAMERA_PARAMS = 29


def camera_params(camera) -> tuple:
    """The camera as the kernels take it (one tuple argument of CAMERA_PARAMS Python floats)."""
    w2c = camera.world_to_camera
    fx, fy, cx, cy, W, H = camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height
    tan_x, tan_y = JACOBIAN_MARGIN * W / (2.0 * fx), JACOBIAN_MARGIN * H / (2.0 * fy)  # 1.3 x tan(half fov), centred
    fisheye = camera.model == "fisheye"
    k = camera.distortion if fisheye else (0.0, 0.0, 0.0, 0.0)
    return (*w2c[:3, :3].ravel().tolist(), *w2c[:3, 3].tolist(), fx, fy, cx, cy, *camera.center.tolist(),
            -(cx / fx + tan_x), (W - cx) / fx + tan_x, -(cy / fy + tan_y), (H - cy) / fy + tan_y,
            1.0 if fisheye else 0.0, *map(float, k), float(camera.max_angle))


def footprint(cam, width, height, means, quats, scales, opacities, i):
    """See the module docstring."""
    wx = np.float64(means[i, 0])
    wy = np.float64(means[i, 1])
    wz = np.float64(means[i, 2])
    o = np.float64(opacities[i])
    x = cam[0] * wx + cam[1] * wy + cam[2] * wz + cam[9]
    y = cam[3] * wx + cam[4] * wy + cam[5] * wz + cam[10]
    z = cam[6] * wx + cam[7] * wy + cam[8] * wz + cam[11]
    if not (z > NEAR) or not (o >= MIN_ALPHA):
        return z, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1, 0, 1, 0
    fx, fy, cx, cy = cam[12], cam[13], cam[14], cam[15]
    qw = np.float64(quats[i, 0])
    qx = np.float64(quats[i, 1])
    qy = np.float64(quats[i, 2])
    qz = np.float64(quats[i, 3])
    qn = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    if qn > 0.0:
        qn = 1.0 / qn
        qw, qx, qy, qz = qw * qn, qx * qn, qy * qn, qz * qn
    else:
        qw = 1.0
    r00 = 1.0 - 2.0 * (qy * qy + qz * qz)
    r01 = 2.0 * (qx * qy - qw * qz)
    r02 = 2.0 * (qx * qz + qw * qy)
    r10 = 2.0 * (qx * qy + qw * qz)
    r11 = 1.0 - 2.0 * (qx * qx + qz * qz)
    r12 = 2.0 * (qy * qz - qw * qx)
    r20 = 2.0 * (qx * qz - qw * qy)
    r21 = 2.0 * (qy * qz + qw * qx)
    r22 = 1.0 - 2.0 * (qx * qx + qy * qy)
    iz = 1.0 / z
    if cam[23] == 0.0:
        # Pinhole. EWA Jacobian rows (fx/z, 0, -fx x'/z), (0, fy/z, -fy y'/z), x' = x/z and y' = y/z
        # clamped to 1.3x the half field of view.
        xz = x * iz
        xz = cam[19] if xz < cam[19] else (cam[20] if xz > cam[20] else xz)
        yz = y * iz
        yz = cam[21] if yz < cam[21] else (cam[22] if yz > cam[22] else yz)
        j00 = fx * iz
        j01 = 0.0
        j02 = -j00 * xz
        j10 = 0.0
        j11 = fy * iz
        j12 = -j11 * yz
        u = fx * (x * iz) + cx
        v = fy * (y * iz) + cy
    else:
        # Fisheye: theta = atan2(r, z) off the axis, theta_d = theta (1 + k1 theta^2 + ... + k4 theta^8),
        # (u, v) = (fx x radial + cx, fy y radial + cy), radial = theta_d / r; that map's Jacobian, unclamped.
        r2 = x * x + y * y
        r = math.sqrt(r2)
        theta = math.atan2(r, z)
        if not (theta < cam[28]):
            return z, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1, 0, 1, 0
        t2 = theta * theta
        theta_d = theta * (1.0 + t2 * (cam[24] + t2 * (cam[25] + t2 * (cam[26] + t2 * cam[27]))))
        slope = 1.0 + t2 * (3.0 * cam[24] + t2 * (5.0 * cam[25] + t2 * (7.0 * cam[26] + t2 * 9.0 * cam[27])))
        rho2 = r2 + z * z
        if r > 1e-7 * z:
            radial = theta_d / r
            ar = (slope * z / rho2 - radial) / r2  # (d radial / d r) / r
        else:  # the limits at the axis
            radial = iz
            ar = (2.0 * cam[24] - 2.0 / 3.0) * iz * iz * iz
        j00 = fx * (radial + x * x * ar)
        j01 = fx * x * y * ar
        j02 = -fx * x * slope / rho2
        j10 = fy * x * y * ar
        j11 = fy * (radial + y * y * ar)
        j12 = -fy * y * slope / rho2
        u = fx * (x * radial) + cx
        v = fy * (y * radial) + cy
    # 2D covariance [[a, b], [b, c]] = (J M)(J M)^T + blur, M = R_cam R S: its columns are the scaled
    # axes in camera space.
    a = 0.0
    b = 0.0
    c = 0.0
    for k in range(3):
        if k == 0:
            g0, g1, g2, s = r00, r10, r20, np.float64(scales[i, 0])
        elif k == 1:
            g0, g1, g2, s = r01, r11, r21, np.float64(scales[i, 1])
        else:
            g0, g1, g2, s = r02, r12, r22, np.float64(scales[i, 2])
        m0 = (cam[0] * g0 + cam[1] * g1 + cam[2] * g2) * s
        m1 = (cam[3] * g0 + cam[4] * g1 + cam[5] * g2) * s
        m2 = (cam[6] * g0 + cam[7] * g1 + cam[8] * g2) * s
        t0 = j00 * m0 + j01 * m1 + j02 * m2
        t1 = j10 * m0 + j11 * m1 + j12 * m2
        a += t0 * t0
        b += t0 * t1
        c += t1 * t1
    a += BLUR
    c += BLUR
    det = a * c - b * b
    if not (det > 0.0):
        return z, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1, 0, 1, 0
    mid = 0.5 * (a + c)
    spread = mid * mid - det
    r = 3.0 * math.sqrt(mid + math.sqrt(0.1 if spread < 0.1 else spread))
    r = 1.0 * math.ceil(1e15 if r > 1e15 else r)  # (clamped: a float beyond int64 has no defined conversion)
    thr = 1.0 * math.log(np.float32(255.0 * o)) + 0.01  # float32 log: the margin covers its rounding
    hx = math.sqrt(2.0 * thr * a)
    hx = r if r < hx else hx
    hy = math.sqrt(2.0 * thr * c)
    hy = r if r < hy else hy
    # The pixel centres k + 0.5 within [u - hx, u + hx]: k from ceil(u - hx - 0.5) to floor(u + hx - 0.5),
    # clipped to the image (the bounds clamped to [-1, width] first, where the integers are exact).
    lo_u = u - hx - 0.5
    hi_u = u + hx - 0.5
    lo_v = v - hy - 0.5
    hi_v = v + hy - 0.5
    u0 = math.ceil(-1.0 if lo_u < -1.0 else (width if lo_u > width else lo_u))
    u1 = math.floor(-1.0 if hi_u < -1.0 else (width if hi_u > width else hi_u))
    v0 = math.ceil(-1.0 if lo_v < -1.0 else (height if lo_v > height else lo_v))
    v1 = math.floor(-1.0 if hi_v < -1.0 else (height if hi_v > height else hi_v))
    u0 = 0 if u0 < 0 else u0
    u1 = width - 1 if u1 > width - 1 else u1
    v0 = 0 if v0 < 0 else v0
    v1 = height - 1 if v1 > height - 1 else v1
    if u0 > u1 or v0 > v1:
        return z, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1, 0, 1, 0
    idet = 1.0 / det
    return z, u, v, 0.5 * c * idet, -b * idet, 0.5 * a * idet, thr, u0, u1, v0, v1


def pixel_ray(cam, u, v):
    """The unit world-space direction R^T d of the ray through image point (u, v) (continuous
    coordinates; a pixel centre is (column + 0.5, row + 0.5)), cam as camera_params; the scalar twin of
    Camera.camera_rays (a fisheye: 10 clamped Newton steps for theta, as fisheye_undistort)."""
    mx = (u - cam[14]) / cam[12]
    my = (v - cam[15]) / cam[13]
    if cam[23] == 0.0:
        n = 1.0 / math.sqrt(mx * mx + my * my + 1.0)
        dx, dy, dz = mx * n, my * n, n
    else:
        theta_d = math.sqrt(mx * mx + my * my)
        theta = cam[28] if theta_d > cam[28] else theta_d
        for _ in range(10):
            t2 = theta * theta
            slope = 1.0 + t2 * (3.0 * cam[24] + t2 * (5.0 * cam[25] + t2 * (7.0 * cam[26] + t2 * 9.0 * cam[27])))
            if slope > 0.0:
                theta -= (theta * (1.0 + t2 * (cam[24] + t2 * (cam[25] + t2 * (cam[26] + t2 * cam[27]))))
                          - theta_d) / slope
            theta = 0.0 if theta < 0.0 else (cam[28] if theta > cam[28] else theta)
        sn = math.sin(theta) / theta_d if theta_d > 0.0 else 1.0
        dx, dy, dz = mx * sn, my * sn, math.cos(theta)
    return (cam[0] * dx + cam[3] * dy + cam[6] * dz, cam[1] * dx + cam[4] * dy + cam[7] * dz,
            cam[2] * dx + cam[5] * dy + cam[8] * dz)
