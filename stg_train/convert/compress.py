"""Shrink a model for shipping: prune, reorder and quantize its attributes (numpy only, no torch).

    compress(model, preset="balanced", ...) -> (Model, Settings)   save: format.save(m, path, **settings.save_kwargs())
    report(original, compressed, settings, views) -> Report        Gaussians, bytes per attribute, PSNR change
    compress_file(in_path, out_path, preset, dataset=None) -> Report

Pruning removes Gaussians the runtime would never draw: those whose peak opacity over the segment,
max over tau in [0, 1] of opacity * exp(-t_scale (tau - t_center)^2), stays below a threshold (below
1/255 the runtime skips them at every time, so that pruning is exact), and those no camera of the file
sees (`unseen`: at no frame time of the segment does any camera get a footprint from them, so
training never saw them either). Ordering sorts the Gaussians along a Morton (Z-order) curve of their
positions, so that neighbours in the file have similar values (renders are unchanged but for
Gaussians at exactly equal depth, whose order the file index breaks).

Quantization stays within formats/stg-v1.md (u8 / u16 with a per-channel offset and scale, f16, f32):
each group of channels (one polynomial coefficient of position or rotation, three feature channels,
one SH band, or the whole attribute) gets a number of bits; the integers are rounded to multiples of
2^(container bits - bits), which zlib stores almost for free. The bits are allocated by measuring:
the renders of a few views (the file's cameras at a few frames, or a dataset's held-out camera) must
stay within the PSNR loss the preset allows (errors against the uncompressed render add to the
model's own error against the ground truth, measured with a dataset or assumed).

The `web` preset uses format 1.5 (formats/stg-v1.md, "Arithmetic-coded fixed point"): each channel
group is a part of its own, B bits as "acB" (2^B levels, arithmetic-coded), as differences where
that takes fewer bytes (the Morton-ordered centres), and a group may become one constant (0 bits:
its mean). It also drops the least important Gaussians (peak opacity x footprint area x time drawn),
the largest of PRUNE_FRACTIONS that costs at most PRUNE_SHARE of the budget, and once the predicted
allocation fits it lowers groups one measured step at a time while the whole stays within budget.
"""
from __future__ import annotations

import json
import math
import os
import zlib
from dataclasses import dataclass, field, replace

import numpy as np

from stg_runtime import format as stg_format
from stg_runtime.model import ATTRIBUTES, Model, Segment
from stg_runtime.player import Player
from stg_runtime.spec import MIN_ALPHA, project_oracle

from ..metrics import psnr_of_mse


@dataclass(frozen=True)
class Preset:
    """max_loss_db: PSNR loss allowed against the ground truth; assumed_psnr: the model's PSNR (dB)
    assumed when no dataset gives it (the budget on the error against the uncompressed render follows
    from both); prune_opacity: peak-opacity threshold (None: no pruning); prune_unseen: drop Gaussians
    no camera sees; order: "morton" or None; level: zlib level; encodings: fixed encodings (None:
    measured within the budget); compact: use format 1.5 (each channel group arithmetic-coded in a part
    of its own, as differences where that is smaller, a group may become one constant, and the least
    important Gaussians are pruned within part of the budget; see prune_least_important)."""

    max_loss_db: float
    assumed_psnr: float = 33.0
    prune_opacity: float | None = MIN_ALPHA
    prune_unseen: bool = True
    order: str | None = "morton"
    level: int = 9
    encodings: dict | None = None
    compact: bool = False


#: The search aims at this fraction of a preset's PSNR loss: a margin for the views it does not render
#: (none when the views are every frame of the held-out cameras: Views.complete).
SAFETY = 0.7

PRESETS = {
    "lossless": Preset(0.0, prune_opacity=None, prune_unseen=False, order=None,
                       encodings={name: "f32" for name in ATTRIBUTES}),
    "balanced": Preset(0.1),
    "small": Preset(0.5, prune_opacity=0.01),
    # without ground truth, a 38 dB model assumed: at 33 dB the demo's 36 dB model lost 0.35 dB
    "web": Preset(0.3, assumed_psnr=38.0, prune_opacity=0.01, compact=True),
}

#: Compact presets prune the least important Gaussians, at most these fractions (largest first), when
#: that costs at most PRUNE_SHARE of the error budget.
PRUNE_FRACTIONS = (0.3, 0.2, 0.1)
PRUNE_SHARE = 0.3


@dataclass
class Settings:
    """What compress did: encodings per attribute, zlib level, pruning and ordering applied, the
    Gaussians removed by each rule, the error budget (MSE against the uncompressed render) and the
    measured error of the chosen encodings, and a log of the encoding search."""

    preset: str
    encodings: dict
    level: int
    prune_opacity: float | None
    prune_unseen: bool
    order: str | None
    removed_opacity: int = 0
    removed_unseen: int = 0
    removed_importance: int = 0
    budget_mse: float | None = None
    measured_mse: float | None = None
    search: list = field(default_factory=list)
    bits: dict = field(default_factory=dict)

    def save_kwargs(self) -> dict:
        """Keyword arguments of stg_runtime.format.save / dumps for the compressed model."""
        return {"encodings": dict(self.encodings), "codec": "zlib", "level": self.level}

    def provenance(self) -> dict:
        return {"preset": self.preset, "encodings": self.encodings, "bits": self.bits, "level": self.level,
                "prune_opacity": self.prune_opacity, "prune_unseen": self.prune_unseen, "order": self.order,
                "removed": {"opacity": self.removed_opacity, "unseen": self.removed_unseen,
                            "importance": self.removed_importance}}


# -- pruning ---------------------------------------------------------------------------------------


def peak_opacity(segment: Segment) -> np.ndarray:
    """(N,) float64 max over tau in [0, 1] of opacity * exp(-t_scale (tau - t_center)^2): the value at
    t_center clamped to [0, 1]."""
    d = np.clip(segment.t_center, 0.0, 1.0).astype(np.float64) - segment.t_center
    return segment.opacity * np.exp(-segment.t_scale.astype(np.float64) * d * d)


def seen_mask(segment: Segment, cameras, margin: float = 1.0) -> np.ndarray:
    """(N,) bool: Gaussians that some camera sees at some frame time tau = j / num_frames: opacity(tau)
    >= 1/255, in front of the near plane, and a footprint (mean +- 3-sigma radius, formats/stg-v1.md
    section 3, widened by `margin` pixels against rounding) that holds a pixel centre of the image."""
    seen = np.zeros(segment.count, bool)
    if not cameras:
        return ~seen
    t_center = segment.t_center.astype(np.float64)
    for j in range(segment.num_frames):
        tau = j / segment.num_frames
        d = tau - t_center
        alive = ~seen & (segment.opacity * np.exp(-segment.t_scale * d * d) >= MIN_ALPHA)
        idx = np.flatnonzero(alive)
        if idx.size == 0:
            continue
        dd = d[idx, None]
        means = np.zeros((idx.size, 3))
        for k in range(segment.position_degree, -1, -1):  # Horner, as the runtime
            means = means * dd + segment.position[idx, k]
        quats = np.zeros((idx.size, 4))
        for k in range(segment.rotation_degree, -1, -1):
            quats = quats * dd + segment.rotation[idx, k]
        for cam in cameras:
            p = project_oracle(means, quats, segment.scale[idx], cam)
            r = p.radius + margin
            u, v = p.mean2d[:, 0], p.mean2d[:, 1]
            hit = (p.visible & (u + r >= 0.5) & (u - r <= cam.width - 0.5)
                   & (v + r >= 0.5) & (v - r <= cam.height - 0.5))
            seen[idx[hit]] = True
            keep = ~hit
            idx, means, quats, dd = idx[keep], means[keep], quats[keep], dd[keep]
            if idx.size == 0:
                break
    return seen


def importance(segment: Segment) -> np.ndarray:
    """(N,) float64 a Gaussian's share of the picture, roughly: peak opacity x the area of its
    footprint (geometric mean scale squared) x the fraction of the segment's time it is drawn (where
    opacity(tau) >= 1/255, at most 1)."""
    peak = peak_opacity(segment)
    t_scale = segment.t_scale.astype(np.float64)
    half = np.sqrt(np.log(np.maximum(peak / MIN_ALPHA, 1.0)) / np.maximum(t_scale, 1e-12))
    area = np.exp(2.0 * np.log(segment.scale.astype(np.float64)).mean(axis=1))
    return peak * area * np.minimum(2.0 * half, 1.0)


def prune_least_important(segment: Segment, fraction: float) -> Segment:
    """The segment without its `fraction` least important Gaussians (see importance), order kept."""
    drop = int(fraction * segment.count)
    if drop == 0:
        return segment
    keep = np.ones(segment.count, bool)
    keep[np.argsort(importance(segment), kind="stable")[:drop]] = False
    return segment.subset(keep)


# -- ordering --------------------------------------------------------------------------------------


def _spread_bits(x: np.ndarray) -> np.ndarray:
    """Interleave two zero bits after each of the low 21 bits of x (uint64)."""
    x = x & np.uint64(0x1FFFFF)
    for shift, mask in ((32, 0x1F00000000FFFF), (16, 0x1F0000FF0000FF), (8, 0x100F00F00F00F00F),
                        (4, 0x10C30C30C30C30C3), (2, 0x1249249249249249)):
        x = (x | (x << np.uint64(shift))) & np.uint64(mask)
    return x


def morton_order(points: np.ndarray, bits: int = 21) -> np.ndarray:
    """(N,) int64 permutation sorting points (N, 3) along a Z-order curve over their bounding box
    (`bits` bits per axis; ties keep their index order)."""
    p = np.asarray(points, np.float64)
    if p.shape[0] == 0:
        return np.zeros(0, np.int64)
    lo, hi = p.min(0), p.max(0)
    cells = (1 << bits) - 1
    q = np.floor((p - lo) / np.where(hi > lo, hi - lo, 1.0) * cells).astype(np.uint64)
    one = np.uint64(1)
    code = _spread_bits(q[:, 0]) | (_spread_bits(q[:, 1]) << one) | (_spread_bits(q[:, 2]) << (one + one))
    return np.argsort(code, kind="stable")


def reorder(segment: Segment) -> Segment:
    """The segment with its Gaussians in Morton order of their positions at the temporal centre."""
    return segment.subset(morton_order(segment.position[:, 0]))


# -- quantization ----------------------------------------------------------------------------------

#: Precision options of a group of channels, cheapest first: fixed-point bits (stored as u8 when every
#: group of the attribute needs <= 8 bits, else u16, with values snapped to multiples of
#: 2^(container bits - bits) so that zlib stores the unused low bits almost for free), then float.
OPTIONS = (1, 2, 3, 4, 5, 6, 7, 8, 10, 12, 14, 16, "f16", "f32")
#: Compact presets (format 1.5) also have 0 bits: the group's channels become their mean.
COMPACT_OPTIONS = (0,) + OPTIONS


def channel_groups(name: str, segment: Segment, kind: str) -> list[slice]:
    """Channels of attribute `name` that share a precision: one polynomial coefficient of position
    (3 channels) or rotation (4), three feature channels (lite / full) or one SH band (sh), else all."""
    if name == "position":
        return [slice(3 * k, 3 * k + 3) for k in range(segment.position_degree + 1)]
    if name == "rotation":
        return [slice(4 * k, 4 * k + 4) for k in range(segment.rotation_degree + 1)]
    if name == "features":
        c = segment.channels
        if kind == "sh":
            bands = int(round(math.sqrt(c // 3)))
            return [slice(3 * band * band, 3 * (band + 1) ** 2) for band in range(bands)]
        return [slice(i, min(i + 3, c)) for i in range(0, c, 3)]
    return [slice(0, math.prod(getattr(segment, name).shape[1:]))]


def container(choice) -> str:
    """The file encoding of a choice: "f16" / "f32" as they are; a list of bits per group -> u8 or u16."""
    if isinstance(choice, str):
        return choice
    return "u8" if max(choice) <= 8 else "u16"


def snapped(values: np.ndarray, choice, groups: list[slice]) -> np.ndarray:
    """`values` (N, ...) as a reader decodes them after writing with `choice` (see OPTIONS).

    Fixed point: the values are quantized with the container's per-channel offset and scale, and
    the integers are rounded to multiples of 2^(container bits - group bits), except that the
    channel's maximum stays at the top level (so that the writer finds the same offset and scale);
    the error is at most 2^(container bits - group bits - 1) scale plus float32 rounding."""
    enc = container(choice)
    stored, params = stg_format.quantize(values, enc)
    if isinstance(choice, str):
        return stg_format.dequantize(stored, enc, params)
    cbits = 8 if enc == "u8" else 16
    levels = (1 << cbits) - 1
    x = values.reshape(values.shape[0], -1).astype(np.float64)
    offset = np.asarray(params["offset"], np.float32).astype(np.float64)
    scale = np.asarray(params["scale"], np.float32).astype(np.float64)
    step = np.ones(x.shape[1])
    for group, bits in zip(groups, choice):
        step[group] = 2.0 ** (cbits - min(bits, cbits))
    q = (x - offset) / np.where(scale > 0, scale, 1.0)
    qs = np.minimum(np.rint(q / step) * step, levels)
    qs = np.where(levels - q < np.abs(q - qs), levels, qs)
    return stg_format.dequantize(qs.astype(stored.dtype).reshape(values.shape), enc, params)


def compact_container(option) -> str:
    """The encoding that holds a compact option's values: "acB" for B bits (format 1.5's
    arithmetic-coded fixed point), "u8" for 0 bits (a constant), "f16" / "f32" as they are."""
    if isinstance(option, str):
        return option
    return f"ac{option}" if option else "u8"


def compact_snapped(values: np.ndarray, choice: list, groups: list[slice]) -> np.ndarray:
    """`values` (N, ...) as a reader decodes them after writing with a compact choice: one option of
    COMPACT_OPTIONS per group, each group in its own container (compact_container); B bits: 2^B
    levels from the channel's minimum to its maximum; 0 bits: the group's channels hold their mean."""
    x = values.reshape(values.shape[0], -1).copy()
    for group, option in zip(groups, choice):
        part = x[:, group]
        if option == 0:
            mean = part.mean(axis=0, dtype=np.float64) if len(part) else np.zeros(part.shape[1])
            x[:, group] = np.broadcast_to(mean.astype(np.float32), part.shape)
        else:
            enc = compact_container(option)
            stored, params = stg_format.quantize(part, enc)
            x[:, group] = stg_format.dequantize(stored, enc, params)
    return x.reshape(values.shape)


def compact_encoding(values: np.ndarray, choice: list, groups: list[slice], level: int) -> str:
    """The format 1.5 encoding string of compact-snapped `values` (N, ...) (see format.save): a part
    per group in its compact_container, the arithmetic-coded ones as differences ("acB-delta") where
    those take fewer bytes (u8 and u16 where zlib at `level` says so); a single part is the plain
    encoding."""
    x = values.reshape(values.shape[0], -1)
    parts = []
    for group, option in zip(groups, choice):
        enc = compact_container(option)
        if enc != "f32" and enc != "f16":
            sizes = {e: encoded_bytes(x[:, group], e, level) for e in (enc, enc + "-delta")}
            enc = min(sizes, key=lambda e: (sizes[e], e))
        parts.append((enc, group.stop - group.start))
    if len(parts) == 1:
        return parts[0][0]
    return "+".join(f"{enc}:{width}" for enc, width in parts)


def quantized(segment: Segment, choices: dict, kind: str) -> Segment:
    """The segment as a reader sees it after writing it with `choices` (attribute -> OPTIONS choice:
    "f32", "f16", "u8", "u16" or a list of bits per channel group; or ("compact", [option per group])
    for compact presets); others stay as they are."""
    arrays = segment.arrays()
    for name, choice in choices.items():
        if isinstance(choice, tuple) and choice[0] == "compact":
            arrays[name] = compact_snapped(arrays[name], choice[1], channel_groups(name, segment, kind))
            continue
        if choice in ("u8", "u16"):
            choice = [8 if choice == "u8" else 16] * len(channel_groups(name, segment, kind))
        groups = channel_groups(name, segment, kind)
        if not isinstance(choice, str):
            choice = list(choice)[:len(groups)]
        arrays[name] = snapped(arrays[name], choice, groups)
    return replace(segment, **arrays)


def quantized_model(model: Model, choices: dict) -> Model:
    return _with_segments(model, [quantized(s, choices, model.kind) for s in model.segments])


def attribute_bytes(model: Model, encodings: dict | None = None, level: int = 6) -> dict[str, int]:
    """Bytes each attribute takes in a file written with `encodings` (default f32) and zlib `level`,
    summed over segments, measured by encoding it as the writer does (blob padding not counted)."""
    encodings = encodings or {}
    out = {name: 0 for name in ATTRIBUTES}
    for seg in model.segments:
        for name, values in seg.arrays().items():
            out[name] += encoded_bytes(values, encodings.get(name, "f32"), level)
    return out


def encoded_bytes(values: np.ndarray, encoding: str, level: int) -> int:
    """Bytes of the blobs format.encode_array writes for `values` with `encoding`: zlib at `level`,
    except blobs stored raw (arithmetic-coded data)."""
    sizes = []

    def blob(payload: bytes, codec: str = "zlib") -> None:
        sizes.append(len(payload) if codec == "raw" else len(zlib.compress(payload, level)))
    stg_format.encode_array(values, encoding, blob)
    return sum(sizes)


def file_attribute_bytes(path) -> dict[str, int]:
    """Bytes each attribute's blobs take in an existing .stg file (from its header), summed over
    segments. The file must be valid (read it with format.load first)."""
    with open(path, "rb") as f:
        prefix = f.read(stg_format.PREFIX.size)
        _, _, _, length = stg_format.PREFIX.unpack(prefix)
        header = json.loads(f.read(length).decode("utf-8"))
    def length(entry: dict) -> int:  # the array's blob, its codebook's and its parts' (format 1.4)
        return (int(entry["data"]["length"]) if "data" in entry else 0) + sum(
            length(e) for e in ([entry["codebook"]] if "codebook" in entry else []) + entry.get("parts", []))

    out = {name: 0 for name in ATTRIBUTES}
    for seg in header["segments"]:
        for name in ATTRIBUTES:
            out[name] += length(seg["attributes"][name])
    return out


# -- rendering views -------------------------------------------------------------------------------


@dataclass
class Views:
    """Where quality is measured: (camera, time in seconds) pairs; references: ground-truth images
    (H, W, 3) in [0, 1] for each view, or None when only the uncompressed render is known; complete:
    the pairs are every frame of the held-out cameras (the search then needs no margin: SAFETY)."""

    pairs: list
    references: list | None = None
    complete: bool = False

    @property
    def source(self) -> str:
        return "dataset" if self.references is not None else "model cameras"


def _segment_frames(model: Model, count: int) -> list[int]:
    """Video frames spread over every segment: `count` in all, at least one per segment."""
    per = max(1, round(count / len(model.segments)))
    frames = []
    for seg in model.segments:
        picks = np.unique(np.linspace(0, seg.num_frames - 1, per).round().astype(int))
        frames += [seg.start_frame + int(j) for j in picks]
    return frames


def model_views(model: Model, max_cameras: int = 3, max_views: int = 9, max_width: int = 320) -> Views:
    """Up to `max_cameras` of the file's cameras (evenly picked; shrunk to at most `max_width` pixels
    wide) at frames spread over every segment (first, middle and last of a single segment), at most
    `max_views` views (at least one per segment). No cameras: no views."""
    cams = list(model.cameras)
    if len(cams) > max_cameras:
        cams = [cams[round(i * (len(cams) - 1) / (max_cameras - 1))] for i in range(max_cameras)]
    cams = [c if c.width <= max_width else c.resized(max_width, max(1, round(c.height * max_width / c.width)))
            for c in cams]
    if not cams:
        return Views([])
    frames = _segment_frames(model, max(1, max_views // len(cams)))
    pairs = [(c, j / model.fps) for j in frames for c in cams]
    if len(pairs) > max(max_views, len(model.segments)):  # many segments: one camera per frame, in turn
        pairs = [(cams[k % len(cams)], j / model.fps) for k, j in enumerate(frames)]
    return Views(pairs)


def dataset_views(dataset, model: Model | None = None, frames: int = 5) -> Views:
    """The dataset's held-out cameras, with ground truth, at `frames` frames spread over the video (over
    every segment of `model`, at least one each, when given)."""
    cams = dataset.test_cameras or dataset.train_cameras[:1]
    if model is None:
        picks = np.unique(np.linspace(0, dataset.num_frames - 1, frames).round().astype(int)).tolist()
    else:
        picks = [j for j in _segment_frames(model, frames) if j < dataset.num_frames]
    pairs = [(dataset.cameras[c], j / dataset.fps) for c in cams for j in picks]
    refs = [dataset.image(c, j) for c in cams for j in picks]
    return Views(pairs, refs, complete=len(picks) == dataset.num_frames)


def render_views(model: Model, views: Views) -> list[np.ndarray]:
    player = Player(model, device="cpu")
    return [player.render(cam, t) for cam, t in views.pairs]


def mse(images: list, references: list) -> float:
    if not images:
        return 0.0
    return float(np.mean([np.mean((np.asarray(a, np.float64) - b) ** 2) for a, b in zip(images, references)]))


def budget_mse(max_loss_db: float, model_mse: float) -> float:
    """The error against the uncompressed render that lowers PSNR by max_loss_db when errors add up:
    model_mse (10^(loss / 10) - 1)."""
    return model_mse * (10.0 ** (max_loss_db / 10.0) - 1.0)


# -- compress --------------------------------------------------------------------------------------


def parse_encodings(text: str) -> dict[str, str]:
    """"position=u16,features=u8" -> {"position": "u16", "features": "u8"}; ValueError names the bad part."""
    out = {}
    for part in filter(None, (p.strip() for p in text.split(","))):
        name, sep, enc = part.partition("=")
        name, enc = name.strip(), enc.strip()
        if not sep or name not in ATTRIBUTES or enc not in stg_format.ENCODINGS:
            raise ValueError(f"bad encoding {part!r}: expected ATTRIBUTE=MODE with ATTRIBUTE one of "
                             f"{', '.join(ATTRIBUTES)} and MODE one of {', '.join(stg_format.ENCODINGS)}")
        out[name] = enc
    return out


def _with_segments(model: Model, segments: list[Segment]) -> Model:
    return Model(model.kind, model.fps, segments, list(model.cameras), model.bounds, dict(model.provenance))


def compress(model: Model, preset: str = "balanced", encodings: dict | None = None,
             prune_opacity: float | None | str = "preset", prune_unseen: bool | None = None,
             order: str | None = "preset", level: int | None = None, views: Views | None = None,
             dataset=None, max_loss_db: float | None = None,
             prune_importance: bool = True) -> tuple[Model, Settings]:
    """Prune, reorder and choose the precision of `model`'s attributes (the model is not modified);
    returns (compressed model, Settings). Write it with `format.save(model, path, **settings.save_kwargs())`.

    preset: "lossless", "balanced", "small" or "web" (PRESETS; web writes format 1.5); the other
    arguments override it:
    encodings: {attribute: "f32" | "f16" | "u8" | "u16"} fixed for those attributes (the others are
    measured); prune_opacity: peak-opacity threshold or None (no pruning); prune_unseen: drop Gaussians
    the file's cameras never see; order: "morton" or None; level: zlib level 0-9. views: where the
    error is measured (default: the dataset's held-out views when `dataset` is given, else
    model_views). With no views at all, unfixed attributes get DEFAULTS_WITHOUT_VIEWS. max_loss_db:
    the PSNR loss allowed (dB; default the preset's; finetune passes what fine-tuning left of it).
    prune_importance: False keeps a compact preset from dropping the least important Gaussians
    (quantisation-aware fine-tuning, whose per-channel ranges must stay those it trained with).
    The returned model holds the values a reader will decode (snapped to the chosen precision).
    """
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r} (expected one of {', '.join(PRESETS)})")
    p = PRESETS[preset] if max_loss_db is None else replace(PRESETS[preset], max_loss_db=float(max_loss_db))
    prune_opacity = p.prune_opacity if prune_opacity == "preset" else prune_opacity
    prune_unseen = p.prune_unseen if prune_unseen is None else bool(prune_unseen)
    order = p.order if order == "preset" else order
    level = p.level if level is None else int(level)
    if order not in (None, "morton"):
        raise ValueError(f"unknown order {order!r} (expected 'morton' or None)")
    if not 0 <= level <= 9:
        raise ValueError(f"zlib level must be 0-9, got {level}")
    fixed = dict(p.encodings or {})
    fixed.update(encodings or {})
    unknown = [f"{k}={v}" for k, v in fixed.items() if k not in ATTRIBUTES or v not in stg_format.ENCODINGS]
    if unknown:
        raise ValueError(f"bad encodings {', '.join(unknown)}")
    settings = Settings(preset, {}, level, prune_opacity, prune_unseen, order)

    segments = []
    for seg in model.segments:
        keep = np.ones(seg.count, bool)
        if prune_opacity is not None:
            keep &= peak_opacity(seg) >= prune_opacity
            settings.removed_opacity += int(seg.count - keep.sum())
        if prune_unseen and model.cameras:
            idx = np.flatnonzero(keep)
            seen = seen_mask(seg.subset(idx), model.cameras)
            settings.removed_unseen += int((~seen).sum())
            keep[idx[~seen]] = False
        seg = seg.subset(keep) if not keep.all() else seg
        segments.append(reorder(seg) if order == "morton" else seg)
    pruned = _with_segments(model, segments)

    free = [name for name in ATTRIBUTES if name not in fixed]
    if views is None:
        views = dataset_views(dataset, model) if dataset is not None else model_views(model)
    if free and not views.pairs:
        fixed.update({name: DEFAULTS_WITHOUT_VIEWS[preset][name] for name in free})
        free = []
    choices = dict(fixed)
    if free:
        found, pruned = _search(model, pruned, views, fixed, free, p, settings, prune_importance)
        choices.update(found)
    out = quantized_model(pruned, choices)
    settings.encodings = {name: _encoding(out, name, choices[name], level) for name in ATTRIBUTES}
    settings.bits = {name: list(choices[name][1] if isinstance(choices[name], tuple) else choices[name])
                     for name in ATTRIBUTES if not isinstance(choices[name], str)}
    out.provenance = {**model.provenance, "compress": settings.provenance()}
    return out, settings


def _encoding(model: Model, name: str, choice, level: int) -> str:
    """The encoding string (format.save) of attribute `name` of the quantized `model` for `choice`."""
    if not (isinstance(choice, tuple) and choice[0] == "compact"):
        return container(choice)
    values = np.concatenate([getattr(s, name) for s in model.segments])
    return compact_encoding(values, choice[1], channel_groups(name, model.segments[0], model.kind), level)


#: Encodings used when there is no camera to measure with: conservative per-attribute choices.
DEFAULTS_WITHOUT_VIEWS = {
    "lossless": {name: "f32" for name in ATTRIBUTES},
    "balanced": {"opacity": "u16", "t_center": "u16", "t_scale": "f16", "position": "f32", "rotation": "f16",
                 "scale": "f16", "features": "f16"},
    "small": {"opacity": "u8", "t_center": "u16", "t_scale": "f16", "position": "u16", "rotation": "u16",
              "scale": "f16", "features": "u8"},
}
DEFAULTS_WITHOUT_VIEWS["web"] = DEFAULTS_WITHOUT_VIEWS["small"]


def _search(original: Model, pruned: Model, views: Views, fixed: dict, free: list, preset: Preset,
            settings: Settings, prune_importance: bool = True) -> dict:
    """The cheapest precision per channel group of the `free` attributes within the preset's budget.

    The budget is the MSE against the uncompressed render that costs SAFETY x preset.max_loss_db of
    PSNR (the whole loss where the views are complete), less what pruning and fixed encodings already
    cost. Each group's own error (only that group reduced) is measured at 8 bits and extrapolated (4x
    per bit) to allocate bits greedily (most error removed per stored bit first). While the measured
    error of the whole model exceeds the budget, the group with the largest own error moves to its
    next option (more bits, then f16, then f32)."""
    before = render_views(original, views)
    model_mse = (mse(before, views.references) if views.references is not None
                 else 10.0 ** (-preset.assumed_psnr / 10.0))
    budget = budget_mse((1.0 if views.complete else SAFETY) * preset.max_loss_db, model_mse)
    if preset.compact and prune_importance:
        pruned = _prune_within(pruned, views, before, PRUNE_SHARE * budget, settings)
    reference = render_views(pruned, views)
    base = mse(reference, before)  # what pruning (and reordering: ties in depth) changed
    options = COMPACT_OPTIONS if preset.compact else OPTIONS

    def error_of(choices: dict) -> float:
        try:
            return mse(render_views(quantized_model(pruned, choices), views), reference)
        except ValueError:  # e.g. values beyond f16's range
            return float("inf")

    base += error_of(fixed) if fixed else 0.0  # and the fixed encodings
    quant_budget = max(budget - base, 0.5 * budget)
    settings.budget_mse = budget
    groups = [(name, g) for name in free
              for g in range(max(len(channel_groups(name, s, pruned.kind)) for s in pruned.segments))]
    own: dict = {}

    def choice_with(name: str, g: int, option) -> object:
        if isinstance(option, str) and not preset.compact:
            return option
        bits = [16] * len([x for x in groups if x[0] == name])
        bits[g] = option
        return ("compact", bits) if preset.compact else bits

    def own_error(name: str, g: int, index: int) -> float:
        if (name, g, index) not in own:
            own[(name, g, index)] = error_of({**fixed, name: choice_with(name, g, options[index])})
        return own[(name, g, index)]

    # Bit allocation: a group's error falls about 4x per bit, from its measured error at 8 bits; every
    # group starts at the fewest bits, then the bit that buys the most error per stored bit goes next
    # until the predicted total fits the budget.
    first = {name: channel_groups(name, pruned.segments[0], pruned.kind) for name in free}
    width = {(name, g): first[name][g].stop - first[name][g].start if g < len(first[name]) else 1
             for name, g in groups}
    at8 = {k: own_error(*k, options.index(8)) for k in groups}

    def predicted(k, i: int) -> float:  # 0 bits (a constant) is measured, and no worse than a constant
        constant = own_error(*k, 0) if options[0] == 0 else float("inf")
        return constant if options[i] == 0 else min(constant, at8[k] * 4.0 ** (8 - options[i]))

    def step(k) -> tuple[float, int]:  # (error removed per stored bit, option index) of k's best move
        i = pick[k]
        return max(((predicted(k, i) - predicted(k, j)) / ((options[j] - options[i]) * width[k]), j)
                   for j in range(i + 1, top + 1))

    pick = {k: 0 for k in groups}

    top = options.index(16)
    total_predicted = sum(predicted(k, 0) for k in groups)
    while total_predicted > quant_budget:
        movable = [k for k in groups if pick[k] < top]
        if not movable:
            break
        best = max(movable, key=step)
        j = step(best)[1]
        total_predicted -= predicted(best, pick[best]) - predicted(best, j)
        pick[best] = j

    def combined(picked: dict | None = None) -> dict:
        picked = pick if picked is None else picked
        out = {}
        for name in free:
            chosen = [options[picked[(n, g)]] for n, g in groups if n == name]
            floats = [o for o in chosen if isinstance(o, str)]
            if preset.compact:
                out[name] = ("compact", chosen)
            else:
                out[name] = max(floats) if floats else chosen  # "f32" > "f16"
        return out

    while True:
        choices = {**fixed, **combined()}
        total = error_of(choices)
        settings.search.append({"choices": {k: v for k, v in choices.items()}, "mse": total})
        movable = [k for k in groups if pick[k] < len(options) - 1]
        if total <= quant_budget or not movable:
            break
        worst = max(movable, key=lambda k: own_error(*k, pick[k]))
        pick[worst] += 1
    if preset.compact:  # what the predictions left of the budget: measured steps down
        total = _tighten(pick, groups, width, options, total, quant_budget,
                         lambda p: error_of({**fixed, **combined(p)}), settings)
    settings.measured_mse = total
    return combined(), pruned


def _stored_bits(option) -> int:
    return {"f16": 16, "f32": 32}.get(option, option)


def _tighten(pick: dict, groups: list, width: dict, options: tuple, total: float, budget: float, error_of,
             settings: Settings) -> float:
    """Lower groups' options one step at a time, each time the step that saves the most stored bits
    per unit of measured error among those that keep the error of the whole within `budget`; stops
    when no step fits. Changes `pick`; returns the final error."""
    while True:
        steps = []
        for k in groups:
            if pick[k] == 0:
                continue
            trial = {**pick, k: pick[k] - 1}
            error = error_of(trial)
            if error <= budget:
                saved = (_stored_bits(options[pick[k]]) - _stored_bits(options[pick[k] - 1])) * width[k]
                steps.append((saved / max(error - total, 1e-12 * budget, 1e-30), k, error))
        if not steps:
            return total
        _, k, total = max(steps, key=lambda step: step[0])
        pick[k] -= 1
        settings.search.append({"lowered": list(k), "option": options[pick[k]], "mse": total})


def _prune_within(pruned: Model, views: Views, before: list, allowed: float, settings: Settings) -> Model:
    """`pruned` without the largest of PRUNE_FRACTIONS of each segment's least important Gaussians
    whose renders stay within `allowed` (MSE against the uncompressed renders `before`); settings
    records how many went."""
    for fraction in PRUNE_FRACTIONS:
        fewer = _with_segments(pruned, [prune_least_important(s, fraction) for s in pruned.segments])
        if mse(render_views(fewer, views), before) <= allowed:
            settings.removed_importance = sum(a.count - b.count for a, b in zip(pruned.segments, fewer.segments))
            return fewer
    return pruned


# -- the report ------------------------------------------------------------------------------------


@dataclass
class Report:
    """Figures of one compression: Gaussians before/after, bytes per attribute before/after, file
    sizes, and quality: `fidelity_db` = PSNR of the compressed renders against the uncompressed ones;
    with ground truth, `psnr_before` / `psnr_after` (dB) on the views."""

    gaussians_before: int
    gaussians_after: int
    bytes_before: dict
    bytes_after: dict
    file_before: int
    file_after: int
    settings: Settings
    views: int = 0
    view_source: str = ""
    fidelity_db: float | None = None
    psnr_before: float | None = None
    psnr_after: float | None = None

    @property
    def psnr_change(self) -> float | None:
        if self.psnr_before is None or self.psnr_after is None:
            return None
        return self.psnr_after - self.psnr_before

    def format(self) -> str:
        s = self.settings
        lines = [f"preset {s.preset}: order {s.order or 'none'}, zlib level {s.level}, "
                 f"prune opacity < {'-' if s.prune_opacity is None else f'{s.prune_opacity:.4g}'}"
                 f"{', unseen' if s.prune_unseen else ''}",
                 f"Gaussians: {self.gaussians_before} -> {self.gaussians_after} "
                 f"(removed {s.removed_opacity} faint, {s.removed_unseen} unseen"
                 f"{f', {s.removed_importance} least important' if s.removed_importance else ''})",
                 f"{'attribute':<10} {'encoding':>8} {'bytes before':>13} {'bytes after':>12} {'ratio':>7}"]
        for name in ATTRIBUTES:
            b, a = self.bytes_before[name], self.bytes_after[name]
            bits = "" if name not in s.bits else " bits " + ",".join(map(str, s.bits[name]))
            encoding = s.encodings[name] if ":" not in s.encodings[name] else "parts"
            parts = "" if encoding != "parts" else " (" + s.encodings[name] + ")"
            lines.append(f"{name:<10} {encoding:>8} {b:>13} {a:>12} {a / max(b, 1):>7.3f}{bits}{parts}")
        lines.append(f"{'file':<10} {'':>8} {self.file_before:>13} {self.file_after:>12} "
                     f"{self.file_after / max(self.file_before, 1):>7.3f}")
        if self.views == 0:
            lines.append("quality: not measured (the file has no cameras; give --data)")
        else:
            fid = "identical" if self.fidelity_db == float("inf") else f"{self.fidelity_db:.2f} dB"
            lines.append(f"quality on {self.views} views ({self.view_source}): PSNR against the uncompressed "
                         f"render {fid}")
            if self.psnr_change is not None:
                lines.append(f"PSNR against ground truth: {self.psnr_before:.3f} -> {self.psnr_after:.3f} dB "
                             f"(change {self.psnr_change:+.3f} dB)")
        return "\n".join(lines)


def report(original: Model, compressed: Model, settings: Settings, views: Views | None = None,
           bytes_before: dict | None = None, file_before: int | None = None) -> Report:
    """Measure a compression. bytes_before / file_before: the input file's figures (default: the
    original written as float32 with zlib level 6, as the trainer writes it)."""
    if bytes_before is None:
        bytes_before = attribute_bytes(original)
    if file_before is None:
        file_before = len(stg_format.dumps(original))
    payload = stg_format.dumps(compressed, **settings.save_kwargs())
    rep = Report(sum(s.count for s in original.segments), sum(s.count for s in compressed.segments),
                 bytes_before, attribute_bytes(compressed, settings.encodings, settings.level),
                 file_before, len(payload), settings)
    views = views if views is not None else model_views(original)
    if views.pairs:
        stored = stg_format.loads(payload, "<compressed>")
        before, after = render_views(original, views), render_views(stored, views)
        rep.views, rep.view_source = len(views.pairs), views.source
        rep.fidelity_db = psnr_of_mse(mse(after, before))
        if views.references is not None:
            rep.psnr_before = float(np.mean([psnr_of_mse(mse([a], [r])) for a, r in zip(before, views.references)]))
            rep.psnr_after = float(np.mean([psnr_of_mse(mse([a], [r])) for a, r in zip(after, views.references)]))
    return rep


def compress_file(in_path, out_path, preset: str = "balanced", dataset=None, **overrides) -> Report:
    """Read `in_path`, compress it (see compress; `dataset` gives held-out views with ground truth),
    write `out_path` atomically, and return the report. Raises FormatError for a bad input file."""
    model = stg_format.load(in_path)
    if dataset is not None:
        end = model.start_frame + model.num_frames
        if model.start_frame > 0 or end < dataset.num_frames or abs(model.fps - dataset.fps) > 1e-6:
            raise ValueError(f"{os.fsdecode(in_path)}: covers frames {model.start_frame}-{end - 1} at "
                             f"{model.fps:g} fps, the dataset {dataset.path or ''} has frames "
                             f"0-{dataset.num_frames - 1} at {dataset.fps:g} fps")
    views = dataset_views(dataset, model) if dataset is not None else model_views(model)
    compressed, settings = compress(model, preset, views=views, **overrides)
    rep = report(model, compressed, settings, views, file_attribute_bytes(in_path), os.path.getsize(in_path))
    stg_format.save(compressed, out_path, **settings.save_kwargs())
    rep.file_after = os.path.getsize(out_path)
    return rep
