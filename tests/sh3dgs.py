"""3D Gaussian Splatting's SH formulas in float64 and INRIA-layout PLY properties, for the SH tests."""
from __future__ import annotations

import numpy as np

from stg_runtime import Camera

C0 = 0.28209479177387814


C1 = 0.4886025119029199


C2 = [1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396]


C3 = [-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
      1.445305721320277, -0.5900435899266435]


REST = {0: 0, 1: 9, 2: 24, 3: 45}


def eval_sh_3dgs(degree, sh, dirs):
    """3DGS's eval_sh in float64: sh (N, 3, K) per channel, dirs (N, 3) unit -> (N, 3)."""
    sh = np.asarray(sh, np.float64)
    x, y, z = (v[:, None] for v in np.asarray(dirs, np.float64).T)  # (N, 1) each, broadcast over channels
    r = C0 * sh[..., 0]
    if degree > 0:
        r = r - C1 * y * sh[..., 1] + C1 * z * sh[..., 2] - C1 * x * sh[..., 3]
    if degree > 1:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        r = (r + C2[0] * xy * sh[..., 4] + C2[1] * yz * sh[..., 5] + C2[2] * (2 * zz - xx - yy) * sh[..., 6]
             + C2[3] * xz * sh[..., 7] + C2[4] * (xx - yy) * sh[..., 8])
    if degree > 2:
        r = (r + C3[0] * y * (3 * xx - yy) * sh[..., 9] + C3[1] * xy * z * sh[..., 10]
             + C3[2] * y * (4 * zz - xx - yy) * sh[..., 11] + C3[3] * z * (2 * zz - 3 * xx - 3 * yy) * sh[..., 12]
             + C3[4] * x * (4 * zz - xx - yy) * sh[..., 13] + C3[5] * z * (xx - yy) * sh[..., 14]
             + C3[6] * x * (xx - 3 * yy) * sh[..., 15])
    return r


def colours_3dgs(degree, sh, means, center):
    d = np.asarray(means, np.float64) - center
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return np.maximum(eval_sh_3dgs(degree, sh, d) + 0.5, 0.0)


def camera(eye=(0.3, -0.2, 0.0), target=(0, 0, 4)):
    return Camera.look_at(list(eye), list(target), [0, -1, 0], 60.0, 64, 48, name="view")


def inria_props(n=60, degree=3, seed=0):
    rng = np.random.default_rng(seed)
    props = {"x": rng.uniform(-1.5, 1.5, n), "y": rng.uniform(-1, 1, n), "z": rng.uniform(3, 5, n),
             "nx": np.zeros(n), "ny": np.zeros(n), "nz": np.zeros(n)}
    props.update({f"f_dc_{i}": rng.normal(0, 1, n) for i in range(3)})
    props.update({f"f_rest_{i}": rng.normal(0, 0.4, n) for i in range(REST[degree])})
    props["opacity"] = rng.normal(0.5, 1.5, n)
    props.update({f"scale_{i}": rng.uniform(-3.2, -1.8, n) for i in range(3)})
    props.update({f"rot_{i}": rng.normal(0, 1, n) for i in range(4)})
    return {k: v.astype(np.float32) for k, v in props.items()}


def inria_sh(props, degree):
    """(N, 3, K) per-channel coefficients read from the INRIA properties (f_rest channel-major)."""
    k = (degree + 1) ** 2
    dc = np.stack([props[f"f_dc_{c}"] for c in range(3)], 1)[:, :, None]
    rest = np.stack([props[f"f_rest_{i}"] for i in range(REST[degree])], 1).reshape(-1, 3, k - 1)
    return np.concatenate([dc, rest], axis=2).astype(np.float64)
