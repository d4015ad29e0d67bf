"""Time evaluation of trainable (raw) Spacetime Gaussian parameters, in torch, and their conversion
to the file's parameters (formats/stg-v1.md, section 2).

Raw parameters follow the paper's reference implementation (see ../shared/reference-implementation-
notes.md). A raw parameter set is a dict of tensors, N Gaussians:

    xyz           (N, 3)    position at the temporal centre (world units)
    motion        (N, 9)    polynomial motion: position(t) = xyz + m[0:3] dt + m[3:6] dt^2 + m[6:9] dt^3
    rotation      (N, 4)    quaternion q (wxyz, any length)
    omega         (N, 4)    rotation velocity: rotation(t) = normalise(q + dt * omega)
    log_scale     (N, 3)    scale = exp(log_scale)
    opacity_logit (N,) or (N, 1)   spatial opacity = sigmoid(opacity_logit)
    t_center      (N,) or (N, 1)   temporal centre mu_t (normalised time)
    t_scale_raw   (N,) or (N, 1)   opacity(t) = sigmoid(opacity_logit) * exp(-(dt / exp(t_scale_raw))^2)
    features      (N, 3) lite (rgb) or (N, 6) full (rgb + view feature)
    time_features (N, 3)    full models only: features(t) = [features, dt * time_features]

with dt = tau - t_center. As in the reference, dt is detached for motion, rotation and the time
features: only the temporal opacity sends gradient to t_center.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

#: Keys of a raw parameter dict (time_features only for full models).
RAW_KEYS = ("xyz", "motion", "rotation", "omega", "log_scale", "opacity_logit", "t_center", "t_scale_raw",
            "features", "time_features")


class Gaussians(NamedTuple):
    """Static 3D Gaussians at one instant, as stg_train.splat.rasterize takes them.
    means (N, 3); quats (N, 4) unit wxyz; scales (N, 3); opacities (N,); features (N, C), C = 3 or 9."""

    means: Tensor
    quats: Tensor
    scales: Tensor
    opacities: Tensor
    features: Tensor


def temporal_opacity(raw: dict[str, Tensor], tau: float) -> Tensor:
    """(N,) sigmoid(opacity_logit) * exp(-((tau - t_center) / exp(t_scale_raw))^2), differentiable in all three."""
    dt = tau - raw["t_center"].reshape(-1)
    s_t = torch.exp(raw["t_scale_raw"].reshape(-1))
    return torch.sigmoid(raw["opacity_logit"].reshape(-1)) * torch.exp(-(dt / s_t) ** 2)


def evaluate(raw: dict[str, Tensor], tau: float) -> Gaussians:
    """The Gaussians of `raw` (see module docstring) at normalised time tau."""
    dt = (tau - raw["t_center"].reshape(-1)).detach()[:, None]  # (N, 1), no gradient to t_center
    m = raw["motion"]
    means = raw["xyz"] + dt * (m[:, 0:3] + dt * (m[:, 3:6] + dt * m[:, 6:9]))
    q = raw["rotation"] + dt * raw["omega"]
    quats = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    features = raw["features"]
    if raw.get("time_features") is not None:
        features = torch.cat([features, dt * raw["time_features"]], dim=-1)
    return Gaussians(means, quats, torch.exp(raw["log_scale"]), temporal_opacity(raw, tau), features)


def to_file_arrays(raw: dict[str, Tensor], dtype=np.float32) -> dict[str, np.ndarray]:
    """The file's attributes (stg_runtime.model.ATTRIBUTES, P = 3, Q = 1) for raw parameters:
    opacity = sigmoid, t_center, t_scale = exp(-2 t_scale_raw), position = [xyz, m0:3, m3:6, m6:9]
    (N, 4, 3), rotation = [q, omega] (N, 2, 4), scale = exp(log_scale), features = [features,
    time_features] (N, 9) full or (N, 3) lite. Computed in float64, returned as `dtype`."""
    with torch.no_grad():
        r = {k: v.detach().to("cpu", torch.float64) for k, v in raw.items() if v is not None}
        n = r["xyz"].shape[0]
        feats = [r["features"]] + ([r["time_features"]] if "time_features" in r else [])
        out = {
            "opacity": torch.sigmoid(r["opacity_logit"].reshape(n)),
            "t_center": r["t_center"].reshape(n),
            "t_scale": torch.exp(-2.0 * r["t_scale_raw"].reshape(n)),
            "position": torch.cat([r["xyz"][:, None], r["motion"].reshape(n, 3, 3)], dim=1),
            "rotation": torch.stack([r["rotation"], r["omega"]], dim=1),
            "scale": torch.exp(r["log_scale"]),
            "features": torch.cat(feats, dim=-1),
        }
    return {k: v.numpy().astype(dtype) for k, v in out.items()}
