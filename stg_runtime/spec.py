"""formats/stg-v1.md in code: its constants, and float64 oracles that transcribe its formulas.

The oracles are slow, whole-array numpy, written to be obviously the spec rather than fast; every
fast path (stg_runtime.timeeval / sh / splat_cpu, stg_runtime.cuda, the trainer's torch splatter) is
tested against them:

    evaluate_oracle(segment, tau)                   the time evaluation (section 2)
    sh_colours_oracle(coeffs, means, centre)        the "sh" colour (section 2, Colour)
    project_oracle(means, quats, scales, camera)    EWA projection (section 3; pinhole and fisheye)
    rasterize_oracle(means, quats, scales, opacities, features, camera)   compositing (section 3)

Inputs (any float dtype, converted to float64): means (M, 3) world positions; quats (M, 4) wxyz,
normalised here (a zero quaternion is the identity); scales (M, 3) standard deviations along the local
axes (world units); opacities (M,) in [0, 1]; features (M, C), any C >= 1; camera: a Camera.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .camera import Camera
from .model import Segment, sh_degree_of, time_channels

# -- section 3: the rendering constants ------------------------------------------------------------
NEAR = 0.01
JACOBIAN_CLAMP = 1.3
#: JACOBIAN_CLAMP - 1: how far beyond the image x/z and y/z may go, in half fields of view.
JACOBIAN_MARGIN = 0.3
BLUR = 0.3
MIN_ALPHA = 1.0 / 255.0
MAX_ALPHA = 0.99
T_STOP = 1e-4


def f32_at_least(x: float) -> np.float32:
    """The smallest float32 >= x, so that for float32 a: (a >= x) == (a >= it), (a < x) == (a < it)."""
    v = np.float32(x)
    return v if float(v) >= x else np.nextafter(v, np.float32(np.inf))


#: The thresholds as float32 splatters compare with them (the same decisions as in float64).
MIN_ALPHA32 = f32_at_least(MIN_ALPHA)
T_STOP32 = f32_at_least(T_STOP)
MAX_ALPHA32 = np.float32(MAX_ALPHA)

# -- section 2: the real SH constants of 3D Gaussian Splatting (degree 0, 1, 2, 3) -----------------
SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
         -0.4570457994644658, 1.445305721320277, -0.5900435899266435)
def sh_basis(dirs: np.ndarray, degree: int) -> np.ndarray:
    """(M, 3) unit directions -> (M, (degree+1)^2) float64 basis values Y_k(dir) (3DGS's constants and signs)."""
    x, y, z = np.asarray(dirs, dtype=np.float64).T
    out = [np.full_like(x, SH_C0)]
    if degree > 0:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree > 1:
        xx, yy, zz = x * x, y * y, z * z
        c2 = SH_C2
        out += [c2[0] * x * y, c2[1] * y * z, c2[2] * (2 * zz - xx - yy), c2[3] * x * z, c2[4] * (xx - yy)]
    if degree > 2:
        c3 = SH_C3
        out += [c3[0] * y * (3 * xx - yy), c3[1] * x * y * z, c3[2] * y * (4 * zz - xx - yy),
                c3[3] * z * (2 * zz - 3 * xx - 3 * yy), c3[4] * x * (4 * zz - xx - yy), c3[5] * z * (xx - yy),
                c3[6] * x * (xx - 3 * yy)]
    return np.stack(out, axis=1)


# -- the oracles -----------------------------------------------------------------------------------
def evaluate_oracle(segment: Segment, tau: float) -> dict[str, np.ndarray]:
    """Every Gaussian of `segment` at normalised time tau (section 2), float64: {"means" (N, 3),
    "quats" (N, 4) unit wxyz, "scales" (N, 3), "opacities" (N,), "features" (N, C)}."""
    d = tau - segment.t_center.astype(np.float64)
    powers = d[:, None] ** np.arange(segment.position_degree + 1)[None, :]
    means = np.einsum("nk,nka->na", powers, segment.position.astype(np.float64))
    rpow = d[:, None] ** np.arange(segment.rotation_degree + 1)[None, :]
    quats = np.einsum("nk,nka->na", rpow, segment.rotation.astype(np.float64))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    feats = segment.features.astype(np.float64).copy()
    tc = time_channels(segment)
    if tc:
        feats[:, -tc:] *= d[:, None]
    opacity = segment.opacity * np.exp(-segment.t_scale.astype(np.float64) * d ** 2)
    return {"means": means, "quats": quats, "scales": segment.scale.astype(np.float64),
            "opacities": opacity, "features": feats}


def sh_colours_oracle(coeffs, means, camera_center) -> np.ndarray:
    """(M, 3) float64 max(SH(dir) + 0.5, 0) per Gaussian: coeffs (M, 3 K) coefficient-major, means (M, 3),
    dir the unit vector from camera_center (3,) to the mean (zero when they coincide)."""
    coeffs = np.asarray(coeffs, dtype=np.float64)
    k = coeffs.shape[1] // 3
    d = np.asarray(means, dtype=np.float64) - np.asarray(camera_center, dtype=np.float64).reshape(1, 3)
    norm = np.linalg.norm(d, axis=1, keepdims=True)
    d = d / np.where(norm > 0, norm, 1.0)
    values = np.einsum("mk,mkc->mc", sh_basis(d, sh_degree_of(coeffs.shape[1])), coeffs.reshape(-1, k, 3))
    return np.maximum(values + 0.5, 0.0)


class Projection(NamedTuple):
    """Per-Gaussian screen-space footprint, float64 (M = number of input Gaussians).

    visible (M,) bool: passed the near-plane and determinant culls (opacity is not looked at here);
    mean2d (M, 2) pixels (unclamped pinhole projection u, v); cov2d (M, 3) the 2D covariance
    [a, b, c] = [[a, b], [b, c]] including the blur (pixels^2); conic (M, 3) [A, B, C] its inverse;
    radius (M,) pixels (ceil of 3 sigma, an integer-valued float); depth (M,) camera-space z.
    Entries of culled Gaussians are 0 (conic, radius) or whatever the formulas gave (the rest).
    """

    visible: np.ndarray
    mean2d: np.ndarray
    cov2d: np.ndarray
    conic: np.ndarray
    radius: np.ndarray
    depth: np.ndarray


def quat_to_rotmat(quats: np.ndarray) -> np.ndarray:
    """(M, 4) wxyz quaternions (any length; zero -> identity) -> (M, 3, 3) rotation matrices."""
    q = np.asarray(quats, dtype=np.float64)
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    q = np.where(norm > 0, q / np.where(norm > 0, norm, 1.0), np.array([1.0, 0.0, 0.0, 0.0]))
    w, x, y, z = q.T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], axis=-1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], axis=-1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=-1),
    ], axis=1)


def fisheye_jacobian(p_cam, camera: Camera) -> np.ndarray:
    """(M, 3) camera-space points (z > 0) -> (M, 2, 3) Jacobians d(u, v) / d(x, y, z) of the fisheye
    projection u = fx x theta_d(theta) / r + cx, v = fy y theta_d(theta) / r + cy (spec section 3),
    r = |(x, y)|, theta = atan2(r, z); on the axis (r <= 1e-7 z), its limit."""
    k1, k2, k3, k4 = camera.distortion
    x, y, z = np.asarray(p_cam, dtype=np.float64).T
    r2 = x * x + y * y
    r = np.sqrt(r2)
    theta = np.arctan2(r, z)
    t2 = theta * theta
    theta_d = theta * (1 + k1 * t2 + k2 * t2**2 + k3 * t2**3 + k4 * t2**4)
    slope = 1 + 3 * k1 * t2 + 5 * k2 * t2**2 + 7 * k3 * t2**3 + 9 * k4 * t2**4  # d theta_d / d theta
    rho2 = r2 + z * z
    off_axis = r > 1e-7 * z
    rs, r2s = np.where(off_axis, r, 1.0), np.where(off_axis, r2, 1.0)
    radial = np.where(off_axis, theta_d / rs, 1 / z)  # theta_d / r
    ar = np.where(off_axis, (slope * z / rho2 - theta_d / rs) / r2s, (2 * k1 - 2 / 3) / z**3)  # radial'(r) / r
    J = np.empty((len(x), 2, 3))
    J[:, 0] = np.stack([camera.fx * (radial + x * x * ar), camera.fx * x * y * ar, -camera.fx * x * slope / rho2], -1)
    J[:, 1] = np.stack([camera.fy * x * y * ar, camera.fy * (radial + y * y * ar), -camera.fy * y * slope / rho2], -1)
    return J


def project_oracle(means, quats, scales, camera: Camera) -> Projection:
    """Project every Gaussian to the image (EWA splatting, spec section 3). See Projection."""
    means = np.asarray(means, dtype=np.float64).reshape(-1, 3)
    scales = np.asarray(scales, dtype=np.float64).reshape(-1, 3)
    W, H = camera.width, camera.height
    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy

    # Camera space, the near plane and (fisheye) the camera's max_angle.
    p_cam = means @ camera.R.T + camera.t
    x, y, z = p_cam.T
    in_front = z > NEAR
    if camera.model == "fisheye":
        in_front &= np.arctan2(np.hypot(x, y), z) < camera.max_angle
    zs = np.where(in_front, z, 1.0)  # avoid dividing by zero for culled Gaussians

    # 2D mean: the unclamped projection.
    mean2d, _ = camera.project(means)

    # 3D covariance R S S^T R^T, rotated to camera space: W Sigma W^T.
    Rg = quat_to_rotmat(quats)
    M = Rg * scales[:, None, :]  # R S
    sigma = M @ M.transpose(0, 2, 1)
    sigma_cam = camera.R @ sigma @ camera.R.T

    if camera.model == "fisheye":
        J = fisheye_jacobian(np.where(in_front[:, None], p_cam, [0.0, 0.0, 1.0]), camera)
    else:
        # EWA Jacobian with x/z, y/z clamped to 1.3 x the half field of view (spec, "Jacobian clamp").
        tan_x, tan_y = W / (2 * fx), H / (2 * fy)
        xz = np.clip(x / zs, -(cx / fx + JACOBIAN_MARGIN * tan_x), (W - cx) / fx + JACOBIAN_MARGIN * tan_x)
        yz = np.clip(y / zs, -(cy / fy + JACOBIAN_MARGIN * tan_y), (H - cy) / fy + JACOBIAN_MARGIN * tan_y)
        J = np.zeros((len(z), 2, 3))
        J[:, 0, 0] = fx / zs
        J[:, 0, 2] = -fx * xz / zs
        J[:, 1, 1] = fy / zs
        J[:, 1, 2] = -fy * yz / zs
    cov = J @ sigma_cam @ J.transpose(0, 2, 1)
    a = cov[:, 0, 0] + BLUR
    b = cov[:, 0, 1]
    c = cov[:, 1, 1] + BLUR

    det = a * c - b * b
    visible = in_front & (det > 0)
    dets = np.where(visible, det, 1.0)
    conic = np.where(visible[:, None], np.stack([c / dets, -b / dets, a / dets], axis=1), 0.0)
    m = 0.5 * (a + c)
    lam_max = m + np.sqrt(np.maximum(0.1, m * m - det))
    radius = np.where(visible, np.ceil(3.0 * np.sqrt(np.where(visible, lam_max, 0.0))), 0.0)
    return Projection(visible, mean2d, np.stack([a, b, c], axis=1), conic, radius, z)


def rasterize_oracle(means, quats, scales, opacities, features, camera: Camera, *, margins=None):
    """Render M Gaussians with the spec's rules, in float64.

    Returns (features (H, W, C), alpha (H, W), depth (H, W)), float64: F = sum w_i f_i,
    alpha = 1 - T_final, depth = sum w_i z_i / alpha (0 where alpha == 0).

    margins: optionally a dict, filled with how close the render came to a threshold, over the
    decisions it took (pixels not yet stopped, inside a footprint), so that tests can tell whether a
    lower-precision splatter can be expected to take the same decisions: "footprint" min ||p - mu| - r|
    (pixels), "power" min |power| (the power < 0 skip), "alpha" min |alpha * 255 - 1| (the 1/255
    floor, relative), "stop" min |T (1 - alpha) / 1e-4 - 1| (the transmittance stop, relative).
    """
    proj = project_oracle(means, quats, scales, camera)
    opacities = np.asarray(opacities, dtype=np.float64).reshape(-1)
    features = np.asarray(features, dtype=np.float64)
    features = features.reshape(len(opacities), features.shape[-1] if features.ndim == 2 else -1)
    H, W, C = camera.height, camera.width, features.shape[1]

    px = (np.arange(W) + 0.5)[None, :]  # pixel centres (1, W)
    py = (np.arange(H) + 0.5)[:, None]  # (H, 1)
    T = np.ones((H, W))
    stopped = np.zeros((H, W), dtype=bool)
    F = np.zeros((H, W, C))
    D = np.zeros((H, W))

    if margins is not None:
        margins.update(footprint=np.inf, power=np.inf, alpha=np.inf, stop=np.inf)
    # Increasing z, ties: lower index first (a stable sort on z).
    order = np.argsort(proj.depth, kind="stable")
    for i in order:
        if not proj.visible[i] or opacities[i] < MIN_ALPHA:
            continue
        mx, my = proj.mean2d[i]
        r = proj.radius[i]
        A, B, Cc = proj.conic[i]
        dx = px - mx
        dy = py - my
        footprint = (np.abs(dx) <= r) & (np.abs(dy) <= r)
        power = 0.5 * (A * dx * dx + Cc * dy * dy) + B * dx * dy
        alpha = np.minimum(MAX_ALPHA, opacities[i] * np.exp(-power))
        take = footprint & (power >= 0) & (alpha >= MIN_ALPHA) & ~stopped
        t_next = T * (1.0 - alpha)
        stop = take & (t_next < T_STOP)
        if margins is not None:
            live = ~stopped & (np.abs(dx) <= r + 1) & (np.abs(dy) <= r + 1)
            edge = np.minimum(np.abs(np.abs(dx) - r) + 0 * dy, np.abs(np.abs(dy) - r) + 0 * dx)
            for key, values, where in (
                    ("footprint", edge, live),
                    ("power", np.abs(power), footprint & live),
                    ("alpha", np.abs(alpha / MIN_ALPHA - 1), footprint & live & (power >= 0)),
                    ("stop", np.abs(t_next / T_STOP - 1), take)):
                if where.any():
                    margins[key] = min(margins[key], float(values[where].min()))
        stopped |= stop
        add = take & ~stop
        w = np.where(add, alpha * T, 0.0)
        F += w[:, :, None] * features[i]
        D += w * proj.depth[i]
        T = np.where(add, t_next, T)

    alpha = 1.0 - T
    depth = np.where(alpha > 0, D / np.where(alpha > 0, alpha, 1.0), 0.0)
    return F, alpha, depth
