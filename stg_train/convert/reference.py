"""Import models trained by the paper's reference implementation (oppo-us-research/SpacetimeGaussians).

Its model is a PLY of raw parameters per Gaussian (../shared/reference-implementation-notes.md):

    x y z trbf_center trbf_scale nx ny nz motion_0..8 f_dc_0..2 (lite) | f_dc_0..5 (full) opacity
    scale_0..2 rot_0..3 omega_0..3 [f_t_0..2 (full)]

plus, for full models, the decoder's torch state dict (`mlp1.weight` [6, 12, 1, 1], `mlp2.weight`
[3, 6, 1, 1], no biases). At reference time t, with dt = t - trbf_center:

    opacity(t)  = sigmoid(opacity) exp(-(dt / exp(trbf_scale))^2)
    position(t) = xyz + motion[0:3] dt + motion[3:6] dt^2 + motion[6:9] dt^3
    rotation(t) = normalise(rot + dt omega);  scale = exp(scale);  features(t) = [f_dc, dt f_t]

The reference's time of frame j of a segment is t = j / duration, `duration` a training setting (50 in
every published configuration; a shorter last segment may be trained with its own length, e.g. 20);
ours is tau = j / num_frames. With k = num_frames / duration, t = k tau, so t_center = trbf_center / k,
dt = k d (d = tau - t_center), and the file's coefficients absorb the powers of k: t_scale =
k^2 exp(-2 trbf_scale), position [xyz, k m0:3, k^2 m3:6, k^3 m6:9], rotation [rot, k omega], time
features k f_t (stg_train.raw.to_file_arrays). When num_frames equals duration nothing is rescaled.
"""
from __future__ import annotations

import os

import numpy as np

from stg_runtime.model import ACTIVATIONS, Model, Segment
from stg_runtime.onnx_mlp import mlp_to_onnx

from ..raw import to_file_arrays
from .ply import float32_values, read_ply, require

#: The reference's default duration: frame j of a segment is at t = j / REFERENCE_FRAMES.
REFERENCE_FRAMES = 50
COMMON = (["x", "y", "z", "trbf_center", "trbf_scale"] + [f"motion_{i}" for i in range(9)] + ["opacity"]
          + [f"scale_{i}" for i in range(3)] + [f"rot_{i}" for i in range(4)] + [f"omega_{i}" for i in range(4)])
LITE = COMMON + [f"f_dc_{i}" for i in range(3)]
FULL = COMMON + [f"f_dc_{i}" for i in range(6)] + [f"f_t_{i}" for i in range(3)]
#: Decoder state dict: key -> shape (1x1 convolutions, out x in x 1 x 1).
DECODER_KEYS = {"mlp1.weight": (6, 12, 1, 1), "mlp2.weight": (3, 6, 1, 1)}


class ReferenceModelError(ValueError):
    """A reference model file that cannot be imported; the message starts with the file's name."""


def read_reference_ply(path) -> tuple[str, dict[str, np.ndarray]]:
    """("full" or "lite", {property: (N,) float64}) of a reference PLY. Raises PLYError naming the file
    (not a PLY, truncated, missing properties, values that are not finite float32 numbers)."""
    columns, _ = read_ply(path)
    kind = "full" if "f_dc_3" in columns or "f_t_0" in columns else "lite"
    require(columns, FULL if kind == "full" else LITE, path)
    return kind, float32_values(columns, FULL if kind == "full" else LITE, path)


def load_decoder(path) -> list[np.ndarray]:
    """The reference decoder's [(6, 12), (3, 6)] float32 weights from its torch state dict, loaded with
    weights_only=True (nothing else is unpickled). Raises ReferenceModelError naming the file."""
    name = os.fsdecode(path)
    try:
        import torch
    except ImportError:
        raise ReferenceModelError(f"{name}: reading a decoder state dict needs torch "
                                  "(python -m pip install torch)") from None
    if not os.path.isfile(path):
        raise ReferenceModelError(f"{name}: no such file")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # torch raises RuntimeError, UnpicklingError, EOFError, ... for bad files
        raise ReferenceModelError(f"{name}: not a readable torch state dict ({type(e).__name__}: "
                                  f"{str(e).splitlines()[0] if str(e) else ''})") from None
    if not isinstance(state, dict):
        raise ReferenceModelError(f"{name}: expected a state dict, got {type(state).__name__}")
    extra = sorted(str(k) for k in state if k not in DECODER_KEYS)
    if extra:
        raise ReferenceModelError(f"{name}: unexpected keys {', '.join(extra)} (the reference decoder has only "
                                  f"{', '.join(DECODER_KEYS)})")
    weights = []
    for key, shape in DECODER_KEYS.items():
        value = state.get(key)
        if not isinstance(value, torch.Tensor):
            raise ReferenceModelError(f"{name}: missing tensor {key!r}")
        if tuple(value.shape) not in (shape, shape[:2]):
            raise ReferenceModelError(f"{name}: {key} has shape {list(value.shape)}, expected {list(shape)}")
        w = value.detach().to(torch.float64).reshape(shape[:2]).numpy()
        if not np.all(np.isfinite(w)):
            raise ReferenceModelError(f"{name}: {key} has non-finite values")
        weights.append(w.astype(np.float32))
    return weights


def reference_segment(kind: str, values: dict[str, np.ndarray], start_frame: int, num_frames: int,
                      decoder: bytes | None = None, activation: str = "sigmoid",
                      duration: float = REFERENCE_FRAMES) -> Segment:
    """A runtime Segment of `num_frames` frames from a reference PLY's raw properties (read_reference_ply),
    rescaling time from t = j / duration to tau = j / num_frames (see the module docstring). The
    reference's raw parameters are ours (stg_train.raw), so stg_train.raw.to_file_arrays converts them."""
    v = values
    cols = lambda prefix, count: np.stack([v[f"{prefix}_{i}"] for i in range(count)], 1)  # noqa: E731
    raw = {"xyz": np.stack([v["x"], v["y"], v["z"]], 1), "motion": cols("motion", 9), "rotation": cols("rot", 4),
           "omega": cols("omega", 4), "log_scale": cols("scale", 3), "opacity_logit": v["opacity"],
           "t_center": v["trbf_center"], "t_scale_raw": v["trbf_scale"],
           "features": cols("f_dc", 6 if kind == "full" else 3)}
    if kind == "full":
        raw["time_features"] = cols("f_t", 3)
    try:
        arrays = to_file_arrays(raw, time_scale=num_frames / duration)
    except ValueError:
        raise ValueError("trbf_scale or scale_* too large or small to exponentiate") from None
    return Segment(start_frame, num_frames, decoder=decoder, activation=activation, **arrays)


def _per_ply(name: str, value, count: int, kind) -> list:
    """`value` (one positive number, or one per PLY) as a list of `count` numbers of `kind`."""
    values = [kind(value)] * count if np.ndim(value) == 0 else [kind(v) for v in value]
    if len(values) != count or not all(v > 0 for v in values):
        raise ValueError(f"{name}: need one positive number, or one per PLY ({count}), got {value}")
    return values


def import_reference(ply_paths, decoder_paths=None, fps: float = 30.0, start_frame: int = 0,
                     segment_frames=REFERENCE_FRAMES, activation: str = "sigmoid", cameras=(),
                     duration=REFERENCE_FRAMES) -> Model:
    """A runtime Model from reference PLYs, one per consecutive segment in time order (with their
    decoder state dicts, one per PLY, for full models).

    fps: frames per second of the video; start_frame: the first segment's first frame;
    segment_frames: frames per segment, one int for all or one per PLY (the last segment of a video
    is often shorter); duration: the reference's `duration` setting each PLY was trained with (frame j
    at t = j / duration), one number for all or one per PLY, default 50 (the official default; a short
    last segment trained with its own length has duration = its frames); activation: the decoder
    output's activation ("sigmoid" for N3V, "clamp" for Technicolor, "identity" for Google Immersive).
    Raises PLYError / ReferenceModelError naming the file, ValueError for inconsistent arguments."""
    ply_paths = [os.fspath(p) for p in ([ply_paths] if isinstance(ply_paths, (str, os.PathLike)) else ply_paths)]
    if not ply_paths:
        raise ValueError("no PLY file given")
    if activation not in ACTIVATIONS:
        raise ValueError(f"activation must be one of {', '.join(ACTIVATIONS)}, got {activation!r}")
    frames = _per_ply("segment_frames", segment_frames, len(ply_paths), int)
    durations = _per_ply("duration", duration, len(ply_paths), float)
    if int(start_frame) < 0:
        raise ValueError(f"start_frame must be >= 0, got {start_frame}")
    decoder_paths = [] if decoder_paths is None else [os.fspath(p) for p in decoder_paths]
    segments, kinds, start = [], [], int(start_frame)
    for i, (path, count, length) in enumerate(zip(ply_paths, frames, durations)):
        kind, values = read_reference_ply(path)
        kinds.append(kind)
        decoder = None
        if kind == "full":
            if len(decoder_paths) != len(ply_paths):
                raise ValueError(f"{path}: a full reference model needs its decoder state dict: give one decoder "
                                 f"per PLY ({len(ply_paths)}), got {len(decoder_paths)}")
            decoder = mlp_to_onnx(load_decoder(decoder_paths[i]))
        elif decoder_paths:
            raise ValueError(f"{path}: a lite reference model has no decoder, but decoders were given")
        try:
            segments.append(reference_segment(kind, values, start, count, decoder, activation, length))
        except ValueError as e:
            raise ReferenceModelError(f"{path}: {e}") from None
        start += count
    if len(set(kinds)) > 1:
        mix = ", ".join(f"{p}: {k}" for p, k in zip(ply_paths, kinds))
        raise ValueError(f"the PLYs mix full and lite models ({mix})")
    xyz = np.concatenate([s.position[:, 0] for s in segments])
    bounds = (tuple(xyz.min(0).tolist()), tuple(xyz.max(0).tolist())) if xyz.size else None
    provenance = {"tool": "stg-convert import-reference", "sources": [os.path.basename(p) for p in ply_paths],
                  "settings": {"fps": fps, "start_frame": int(start_frame), "segment_frames": frames,
                               "duration": durations, "activation": activation}}
    return Model(kinds[0], fps, segments, list(cameras), bounds, provenance)
