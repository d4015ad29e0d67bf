"""Straight-through fake quantisation of a model's file attributes (issue 50, item 4; torch).

    file_tensors(raw) -> {attribute: Tensor}                  the file's attributes of raw parameters
    written(values, choice, groups) -> ndarray                what a reader decodes after the web writer
    fake_quantised(values, choice, groups) -> Tensor          forward: written; gradient: identity
    quantised_tensors(raw, choices, like, kind) -> {attribute: Tensor}
    snapped_segment(raw, bits, like, kind, decoder) -> Segment  the values handed to the writer
    gaussians_of_file(arrays, tau) -> Gaussians               the runtime's evaluation (formats/stg-v1.md, 2)
    lowered(bits, steps) -> list                              a compact choice `steps` options cheaper

Quantisation-aware fine-tuning renders what a reader decodes: the raw parameters become the file's
attributes (as stg_train.raw.to_file_arrays with time scale 1, in float32), each attribute goes
through the writer's quantisation at the chosen bits (compress.compact_snapped, the very function the
web preset's search and writer use: B bits are 2^B levels per channel from the current values'
minimum to their maximum, with 0 on a level where they span it; stg_runtime.format.quantize), and
the Gaussians are evaluated from those values (`written`: the snapped values once more through their
encoding, as the writer stores them). The forward value is exactly the decoded value (float32); the
gradient passes straight through the rounding (d quantised / d value = 1).
"""
from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from stg_runtime import format as stg_format
from stg_runtime.model import Segment

from ..params import Gaussians
from .compress import COMPACT_OPTIONS, channel_groups, compact_container, compact_snapped


def file_tensors(raw: dict[str, Tensor]) -> dict[str, Tensor]:
    """The file's attributes (float32, differentiable) of raw parameters (stg_train.raw's table, time
    scale 1): opacity, t_center, t_scale (N,), position (N, 4, 3), rotation (N, 2, 4), scale (N, 3),
    features (N, 3 lite / 9 full)."""
    n = raw["xyz"].shape[0]
    features = [raw["features"]] + ([raw["time_features"]] if raw.get("time_features") is not None else [])
    return {"opacity": torch.sigmoid(raw["opacity_logit"].reshape(n)),
            "t_center": raw["t_center"].reshape(n),
            "t_scale": torch.exp(-2.0 * raw["t_scale_raw"].reshape(n)),
            "position": torch.cat([raw["xyz"][:, None], raw["motion"].reshape(n, 3, 3)], dim=1),
            "rotation": torch.stack([raw["rotation"], raw["omega"]], dim=1),
            "scale": torch.exp(raw["log_scale"]),
            "features": torch.cat(features, dim=-1)}


def written(values: np.ndarray, choice: list, groups: list[slice]) -> np.ndarray:
    """`values` (N, ...) float32 as a reader decodes the file after the web writer stores their
    compact-snapped values (compress.compact_snapped, one COMPACT_OPTIONS entry per channel group):
    each group's encoding (compress.compact_container) quantised and dequantised once more as
    format.save does (it finds a scale up to an ulp larger than the snapping's)."""
    x = compact_snapped(np.asarray(values, np.float32), list(choice), groups).reshape(values.shape[0], -1)
    for group, option in zip(groups, choice):
        enc = compact_container(option)
        stored, params = stg_format.quantize(x[:, group], enc)
        x[:, group] = stg_format.dequantize(stored, enc, params)
    return x.reshape(values.shape)


def fake_quantised(values: Tensor, choice: list, groups: list[slice]) -> Tensor:
    """`values` (N, ...) float32 with the forward value `written` (what a reader decodes after the
    web writer stores them with the compact `choice`) and the gradient of the identity
    (straight-through)."""
    decoded = written(values.detach().cpu().numpy(), choice, groups)
    return torch.from_numpy(np.ascontiguousarray(decoded)).to(values) + (values - values.detach())


def quantised_tensors(raw: dict[str, Tensor], choices: dict, like: Segment, kind: str) -> dict[str, Tensor]:
    """file_tensors(raw) with each attribute of `choices` ({attribute: [option per channel group]}, as
    compress's Settings.bits) fake-quantised; `like`: a segment of the same layout (channel groups)."""
    arrays = file_tensors(raw)
    for name, choice in choices.items():
        arrays[name] = fake_quantised(arrays[name], choice, channel_groups(name, like, kind))
    return arrays


def gaussians_of_file(arrays: dict[str, Tensor], tau: float) -> Gaussians:
    """The Gaussians of file attributes at normalised time tau, as the runtime evaluates them
    (dt = tau - t_center: Horner on the position coefficients, rotation normalised, opacity x
    exp(-t_scale dt^2), the last 3 feature channels of a full model times dt). As in training, dt is
    detached for motion, rotation and features: only opacity sends gradient to t_center."""
    dt_full = tau - arrays["t_center"]
    dt = dt_full.detach()[:, None]
    pos = arrays["position"]
    means = pos[:, -1]
    for k in range(pos.shape[1] - 2, -1, -1):
        means = means * dt + pos[:, k]
    rot = arrays["rotation"]
    q = rot[:, -1]
    for k in range(rot.shape[1] - 2, -1, -1):
        q = q * dt + rot[:, k]
    quats = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    features = arrays["features"]
    if features.shape[1] == 9:  # full: 6 base channels, 3 time channels
        features = torch.cat([features[:, :6], dt * features[:, 6:]], dim=-1)
    opacity = arrays["opacity"] * torch.exp(-arrays["t_scale"] * dt_full ** 2)
    return Gaussians(means, quats, arrays["scale"], opacity, features)


def lowered(bits: list, steps: int = 1) -> list:
    """A compact choice (COMPACT_OPTIONS per group) with each fixed-point group `steps` options
    cheaper (10 -> 8 -> 7 ... -> 1 bit; never to 0, a constant, unless it was one); f16 / f32 stay."""
    out = []
    for option in bits:
        if isinstance(option, str) or option == 0:
            out.append(option)
            continue
        out.append(COMPACT_OPTIONS[max(1, COMPACT_OPTIONS.index(option) - steps)])
    return out


def snapped_segment(raw: dict[str, Tensor], bits: dict, like: Segment, kind: str, decoder) -> Segment:
    """A file segment of raw parameters whose attributes of `bits` are compact-snapped (the values
    the web writer is handed, which a reader decodes as quantised_tensors' forward), with `like`'s
    frames, activation and channel groups and the ONNX `decoder` (bytes or None)."""
    values = {k: v.detach().cpu().numpy().astype(np.float32) for k, v in file_tensors(raw).items()}
    for name, choice in bits.items():
        values[name] = compact_snapped(values[name], list(choice), channel_groups(name, like, kind))
    return Segment(like.start_frame, like.num_frames, decoder=decoder, activation=like.activation,
                   context_frames=like.context_frames, **values)
