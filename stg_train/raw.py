"""The raw parameterisation of Spacetime Gaussians (the paper's reference implementation's; numpy only),
and its one conversion to the file's attributes (formats/stg-v1.md, section 2).

The trainer optimises these raw values (stg_train.params holds them as torch tensors and evaluates them
at a time); the reference implementation's PLYs store the same values (stg_train.convert.reference).
Per Gaussian (N rows), with dt the time since the temporal centre:

    xyz           (N, 3)    position at the temporal centre (world units)
    motion        (N, 9)    polynomial motion: position(t) = xyz + m[0:3] dt + m[3:6] dt^2 + m[6:9] dt^3
    rotation      (N, 4)    quaternion q (wxyz, any length)
    omega         (N, 4)    rotation velocity: rotation(t) = normalise(q + dt * omega)
    log_scale     (N, 3)    scale = exp(log_scale)
    opacity_logit (N,) or (N, 1)   spatial opacity = sigmoid(opacity_logit)
    t_center      (N,) or (N, 1)   temporal centre mu_t
    t_scale_raw   (N,) or (N, 1)   opacity(t) = sigmoid(opacity_logit) * exp(-(dt / exp(t_scale_raw))^2)
    features      (N, 3) lite (rgb) or (N, 6) full (rgb + view feature)
    time_features (N, 3)    full models only: features(t) = [features, dt * time_features]

Time (dt) is the raw model's own: for our trainer the file's normalised time tau = j / num_frames of a
segment's frame j; for the reference implementation t = j / duration, which to_file_arrays maps to tau
through its time_scale.
"""
from __future__ import annotations

import numpy as np

#: Keys of a raw parameter dict (time_features only for full models).
RAW_KEYS = ("xyz", "motion", "rotation", "omega", "log_scale", "opacity_logit", "t_center", "t_scale_raw",
            "features", "time_features")


def sigmoid(x: np.ndarray) -> np.ndarray:
    """1 / (1 + exp(-x)) without overflow for large |x| (float64)."""
    return 0.5 * (1.0 + np.tanh(0.5 * np.asarray(x, np.float64)))


def to_file_arrays(raw: dict, time_scale: float = 1.0, dtype=np.float32) -> dict[str, np.ndarray]:
    """The file's attributes (stg_runtime.model.ATTRIBUTES, position degree 3, rotation degree 1) of raw
    parameters (arrays as in the module docstring; torch tensors are not accepted: pass .numpy()).

    time_scale k: the raw time of a segment's frame j is k * tau, tau = j / num_frames the file's time
    (k = 1 for our trainer; num_frames / duration for the reference's t = j / duration). The file's
    coefficients absorb the powers of k: t_center / k, t_scale = k^2 exp(-2 t_scale_raw), position
    [xyz, k m0:3, k^2 m3:6, k^3 m6:9], rotation [q, k omega], time features k * time_features.
    opacity = sigmoid(opacity_logit), scale = exp(log_scale). Computed in float64, returned as `dtype`;
    ValueError when a value does not fit (exp overflows), t_scale capped at float32's largest value.
    """
    r = {k: np.asarray(v, np.float64) for k, v in raw.items() if v is not None}
    n = r["xyz"].shape[0]
    k = float(time_scale)
    motion = r["motion"].reshape(n, 3, 3) * (k ** np.arange(1, 4))[None, :, None]
    features = [r["features"]] + ([k * r["time_features"]] if "time_features" in r else [])
    with np.errstate(over="ignore"):
        t_scale = k * k * np.exp(-2.0 * r["t_scale_raw"].reshape(n))
        scale = np.exp(r["log_scale"])
    if not (np.all(np.isfinite(t_scale)) and np.all(np.isfinite(scale.astype(dtype)))):
        raise ValueError("t_scale_raw or log_scale too large or small to exponentiate")
    out = {
        "opacity": sigmoid(r["opacity_logit"].reshape(n)),
        "t_center": r["t_center"].reshape(n) / k,
        "t_scale": np.minimum(t_scale, np.finfo(np.float32).max),
        "position": np.concatenate([r["xyz"][:, None], motion], axis=1),
        "rotation": np.stack([r["rotation"], k * r["omega"]], axis=1),
        "scale": scale,
        "features": np.concatenate(features, axis=-1),
    }
    return {name: v.astype(dtype) for name, v in out.items()}
