"""Compression with fine-tuning against the training frames (issue 50, item 4; torch).

    params_of(segment, kind) -> STGParams                        a file segment as trainable raw tensors
    finetune(model, dataset, steps, prune=0, stages=1, still=0) -> Model  N photometric steps on the training cameras
    prune_schedule(count, steps, prune, stages) -> {step: kept}  when fine-tuning prunes, and to how many
    contribution(params, dataset, views) -> (N,)                 blending weight summed over training views
    finetune_quantised(model, dataset, steps, bits) -> Model     the same through fake quantisation (qat.py)
    compress_finetuned(model, dataset, steps, preset, prune, ...) -> (Model, Settings, FinetuneInfo)
    finetune_file(in_path, out_path, dataset, steps, preset, prune, ...) -> (Report, FinetuneInfo)

The recipe measured in docs/convert.md ("Fine-tuning"): fine-tune for `steps` steps against the
training cameras' frames (the trainer's loss, L1 + D-SSIM, Adam at the trainer's rates times
LR_SCALE, no densification) while dropping the `prune` Gaussians that contribute least to the
training views (contribution: blending weight summed over random views, of the values at the
time) in PRUNE_STAGES equal shares over the first half of the steps, and with `still`, holding the
Gaussians whose centre moves less than `still` x the scene's extent while drawn (still.py) at zero
motion and rotation velocity, chosen again after each pruning; then compress the result with the
preset, whose error budget is what is left of the preset's PSNR loss after what pruning and
fine-tuning cost on the held-out views, or the loss plus what they gained (measured against the
original model's PSNR there).
Fine-tuning recovers most of what pruning lost, so the file has fewer Gaussians at the same
quantisation. With quantised_steps, the compressed model is then fine-tuned through straight-through
fake quantisation one option below the bits chosen (QAT_LOWER) and searched again without pruning;
the smaller file within the loss is kept.

Only one-segment models (what `stg-train` writes for one segment); the decoder is fine-tuned too.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from stg_runtime import format as stg_format
from stg_runtime.model import Model, Segment
from stg_runtime.onnx_mlp import mlp_to_onnx, read_mlp

from ..losses import loss_fn
from ..params import DecoderMLP, LearningRates, STGParams, extent_of
from ..raw import to_file_arrays
from ..render import rasterize, resolve_backend
from ..trainer import frame_time
from ..strategy.ops import keep_gaussians
from .compress import (PRESETS, Report, Settings, _with_segments, compress, dataset_views, file_attribute_bytes,
                       mse, render_views, report)
from ..metrics import psnr_of_mse
from .qat import gaussians_of_file, lowered, quantised_tensors, snapped_segment
from .still import still_mask

#: Fine-tuning rates: the trainer's (params.LearningRates, positions at their final rate) times this.
LR_SCALE = 0.5
#: Quantisation-aware steps' rates: the trainer's times this (0.5 and 0.2 lost 0.1-0.4 dB more, docs).
QAT_LR_SCALE = 0.05
#: Pruning while fine-tuning: in this many stages (1: all before the first step), spread over this
#: share of the steps (docs/convert.md, "Fine-tuning").
PRUNE_STAGES = 5
PRUNE_SPAN = 0.5
#: The held-out camera's frames (spread over the video; all of a 30-frame clip) on which pruning,
#: fine-tuning and the preset's search are measured (compress's own default, 5, misjudges the loss
#: of fine-tuned models: docs/convert.md, "Fine-tuning"). Where they are every frame, the search keeps
#: no margin (compress.Views.complete).
VIEW_FRAMES = 30
#: Pruning while fine-tuning ranks the Gaussians by their blending weight summed over this many random
#: training views (contribution; 60 and 300 views prune alike, docs/convert.md).
CONTRIBUTION_VIEWS = 60
#: Quantisation-aware fine-tuning renders at the first search's bits this many options lower.
QAT_LOWER = 1


@dataclass
class FinetuneInfo:
    """What fine-tuning did: Gaussians before / after pruning, steps, seconds, and the held-out PSNR
    (dB, mean over the dataset_views) of the original, of it pruned at once (before any step) and
    of the fine-tuned model."""

    gaussians: int
    kept: int
    steps: int
    seconds: float
    psnr_original: float
    psnr_pruned: float
    psnr_finetuned: float
    still: int = 0
    quantised_steps: int = 0
    psnr_quantised: float | None = None
    quantised_kept: bool = False
    candidates: list = field(default_factory=list)

    def format(self) -> str:
        return (f"fine-tune: {self.gaussians} -> {self.kept} Gaussians, {self.steps} steps in {self.seconds:.0f} s; "
                f"held-out PSNR {self.psnr_original:.2f} dB, pruned {self.psnr_pruned:.2f}, "
                f"fine-tuned {self.psnr_finetuned:.2f}"
                + (f"; {self.still} of them still" if self.still else "")
                + ("" if not self.quantised_steps else
                   f"; {self.quantised_steps} quantisation-aware steps: {self.psnr_quantised:.2f} dB, "
                   f"searched again: {self.candidates[1][0]} bytes at {self.candidates[1][1]:.2f} dB against "
                   f"{self.candidates[0][0]} at {self.candidates[0][1]:.2f} first, "
                   f"{'kept' if self.quantised_kept else 'not kept'}"))


def params_of(segment: Segment, kind: str) -> STGParams:
    """The trainable raw parameters of a file segment (the inverse of raw.to_file_arrays with time
    scale 1): xyz (N, 3), motion (N, 9), rotation / omega (N, 4), log_scale (N, 3), opacity_logit,
    t_center, t_scale_raw (N, 1), features (N, 6 full / 3 lite), time_features (N, 3, full)."""
    n = segment.count
    f64 = lambda a: np.asarray(a, np.float64)  # noqa: E731
    pos, rot, feat = f64(segment.position), f64(segment.rotation), f64(segment.features)
    opacity = np.clip(f64(segment.opacity), 1e-6, 1 - 1e-6)
    base = 6 if kind == "full" else 3
    raw = {"xyz": pos[:, 0], "motion": pos[:, 1:4].reshape(n, 9), "rotation": rot[:, 0], "omega": rot[:, 1],
           "log_scale": np.log(np.maximum(f64(segment.scale), 1e-12)),
           "opacity_logit": np.log(opacity / (1 - opacity)).reshape(n, 1),
           "t_center": f64(segment.t_center).reshape(n, 1),
           "t_scale_raw": -0.5 * np.log(np.maximum(f64(segment.t_scale), 1e-30)).reshape(n, 1),
           "features": feat[:, :base]}
    if kind == "full":
        raw["time_features"] = feat[:, base:base + 3]
    decoder = None
    if kind == "full":
        mlp = read_mlp(segment.decoder)
        decoder = DecoderMLP(mlp.input_width, mlp.weights[0].shape[0])
        with torch.no_grad():
            decoder.layer1.weight.copy_(torch.as_tensor(mlp.weights[0]))
            decoder.layer2.weight.copy_(torch.as_tensor(mlp.weights[1]))
    return STGParams({k: torch.as_tensor(v, dtype=torch.float32) for k, v in raw.items()}, kind, decoder=decoder)


def _segment_of(params: STGParams, like: Segment) -> Segment:
    """A file segment of `params` with `like`'s frames and decoder activation."""
    arrays = to_file_arrays({k: v.detach().cpu().numpy() for k, v in params.raw.items()})
    decoder = None if params.decoder is None else mlp_to_onnx(params.decoder.weights())
    return Segment(like.start_frame, like.num_frames, decoder=decoder, activation=like.activation,
                   context_frames=like.context_frames, **arrays)


def _check(model: Model, dataset) -> None:
    if len(model.segments) != 1:
        raise ValueError(f"fine-tuning takes a one-segment model, this one has {len(model.segments)}")
    seg = model.segments[0]
    if seg.start_frame != 0 or seg.num_frames != dataset.num_frames or any(seg.context_frames):
        raise ValueError(f"the model covers frames {seg.start_frame}-{seg.start_frame + seg.num_frames - 1}, "
                         f"the dataset 0-{dataset.num_frames - 1}")
    if model.kind == "full" and (seg.decoder is None or seg.activation != "sigmoid"):
        raise ValueError("fine-tuning needs the trainer's decoder (12 -> 6 -> 3, sigmoid)")


def prune_schedule(count: int, steps: int, prune: float, stages: int) -> dict[int, int]:
    """{step: Gaussians kept from that step on}: `stages` prunings evenly spread over the first
    PRUNE_SPAN of `steps`, each keeping the same share of what is left, the last keeping
    count - int(prune * count) of the `count`; {} when nothing is pruned."""
    final = count - int(prune * count)
    if final >= count:
        return {}
    stages = max(1, min(int(stages), int(steps * PRUNE_SPAN)))
    schedule = {}
    for i in range(stages):
        kept = count * (final / count) ** ((i + 1) / stages)
        schedule[int(i * steps * PRUNE_SPAN / stages)] = final if i + 1 == stages else max(final, int(round(kept)))
    return schedule


def finetune(model: Model, dataset, steps: int, seed: int = 0, lr_scale: float = LR_SCALE,
             prune: float = 0.0, stages: int = 1, still: float = 0.0) -> Model:
    """`model` (one segment, frames 0..dataset.num_frames-1) after `steps` Adam steps of the trainer's
    loss on one random training camera and frame each; no Gaussian is added. With `prune`, those
    that contribute least (contribution, of the current values) are removed in `stages` prunings
    (prune_schedule), the fraction `prune` (0-1) of them in all. With `still` > 0, the Gaussians
    whose centre moves less than `still` x the training cameras' extent (params.extent_of) while
    drawn get motion and rotation velocity 0 and keep them (still.still_mask; chosen before the first
    step and again after each pruning)."""
    _check(model, dataset)
    seg = model.segments[0]
    params = params_of(seg, model.kind)
    _tune(params, dataset, steps, seed, lr_scale, prunes=prune_schedule(seg.count, steps, prune, stages), like=seg,
          still=still)
    with torch.no_grad():
        return _with_segments(model, [_segment_of(params, seg)])


def finetune_quantised(model: Model, dataset, steps: int, bits: dict, seed: int = 0,
                       lr_scale: float = QAT_LR_SCALE) -> Model:
    """`model` after `steps` fine-tuning steps (as finetune) that render it through straight-through
    fake quantisation at `bits` ({attribute: [COMPACT_OPTIONS entry per channel group]}, as
    compress's Settings.bits; stg_train.convert.qat); the returned model holds the quantised values
    (what the web writer stores at those bits), the decoder in float."""
    _check(model, dataset)
    seg = model.segments[0]
    params = params_of(seg, model.kind)
    _tune(params, dataset, steps, seed, lr_scale, bits, seg)
    with torch.no_grad():
        decoder = None if params.decoder is None else mlp_to_onnx(params.decoder.weights())
        return _with_segments(model, [snapped_segment(params.raw, bits, seg, model.kind, decoder)])


def _tune(params: STGParams, dataset, steps: int, seed: int, lr_scale: float, bits: dict | None = None,
          like: Segment | None = None, prunes: dict[int, int] | None = None, still: float = 0.0) -> None:
    """`steps` Adam steps on `params` (in place): the trainer's loss on one random training camera and
    frame each, rendered through fake quantisation at `bits` (segment layout `like`) when given; at
    each step of `prunes` only that many Gaussians, those that contribute most, are kept (with their
    Adam state). With `still` > 0, the still Gaussians (see finetune) are chosen at step 0 and at each
    step of `prunes`, and their motion and rotation velocity are set to 0 after every Adam step."""
    lr = LearningRates().scaled(lr_scale)
    extent = extent_of([dataset.cameras[i] for i in dataset.train_cameras])
    groups = params.param_groups(replace(lr, xyz_init=lr.xyz_final), extent)
    optimizer = torch.optim.Adam(groups, eps=1e-15)
    rng = np.random.default_rng(seed)
    backend = resolve_backend("auto", "cpu")
    choose_still = {0, *(prunes or {})} if still > 0 else set()
    held = None
    for step in range(int(steps)):
        if prunes and step in prunes:
            _keep_top_contributors(params, optimizer, prunes.pop(step), dataset, backend, seed + step)
        if step in choose_still:
            held = _hold_still(params, still * extent, like)
        ci, frame = _random_view(rng, dataset)
        cam = dataset.cameras[ci]
        tau = frame_time(dataset, frame)
        if bits is None:
            g = params.at(tau)
        else:
            g = gaussians_of_file(quantised_tensors(params.raw, bits, like, params.kind), tau)
        out = rasterize(g.means, g.quats, g.scales, g.opacities, g.features, cam, backend=backend)
        img = params.colour(out.features, cam)
        gt = torch.from_numpy(dataset.frame(ci, frame)).float() / 255.0
        loss = loss_fn(img[None], gt[None])
        loss.backward()
        optimizer.step()
        optimizer.zero_grad(set_to_none=True)
        if held is not None:
            _zero_velocities(params, held)
    for kept in (prunes or {}).values():  # no steps: prune all the same
        _keep_top_contributors(params, optimizer, kept, dataset, backend, seed)
    if choose_still and int(steps) <= 0:
        _hold_still(params, still * extent, like)


def _hold_still(params: STGParams, distance: float, like: Segment) -> torch.Tensor:
    """(N,) bool: the Gaussians of `params` whose centre moves less than `distance` (world units) while
    drawn over `like`'s frames (still.still_mask, of the current values); their motion and rotation
    velocity are set to 0."""
    arrays = to_file_arrays({k: v.detach().cpu().numpy() for k, v in params.raw.items()})
    mask = torch.from_numpy(still_mask(Segment(0, like.num_frames, **arrays), distance))
    _zero_velocities(params, mask)
    return mask


def _zero_velocities(params: STGParams, mask: torch.Tensor) -> None:
    """Set the motion and rotation velocity (omega) rows of `mask` (N,) bool to 0, in place."""
    with torch.no_grad():
        params.raw["motion"][mask] = 0.0
        params.raw["omega"][mask] = 0.0


def _random_view(rng: np.random.Generator, dataset) -> tuple[int, int]:
    """(camera index, frame): a random training camera of `dataset` at a random frame."""
    train = dataset.train_cameras
    return int(train[rng.integers(len(train))]), int(rng.integers(dataset.num_frames))


def contribution(params: STGParams, dataset, views: int = CONTRIBUTION_VIEWS, seed: int = 0,
                 backend: str = "numba") -> np.ndarray:
    """(N,) float64: each Gaussian's blending weight (transmittance x alpha), summed over the pixels of
    `views` random training cameras at random frames, at the current values: its share of what those
    views show, occlusion included. The sum is the gradient of the splatted image of a constant
    one-channel feature with respect to that feature."""
    rng = np.random.default_rng(seed)
    score = np.zeros(params.count)
    for _ in range(int(views)):
        ci, frame = _random_view(rng, dataset)
        with torch.no_grad():
            g = params.at(frame_time(dataset, frame))
        probe = torch.ones(params.count, 1, requires_grad=True)
        out = rasterize(g.means, g.quats, g.scales, g.opacities, probe, dataset.cameras[ci], backend=backend)
        out.features.sum().backward()
        score += probe.grad[:, 0].double().numpy()
    return score


def _keep_top_contributors(params: STGParams, optimizer, kept: int, dataset, backend: str, seed: int) -> None:
    """Keep the `kept` Gaussians of `params` that contribute most to the training views (contribution),
    values, order and Adam moments (strategy.ops.keep_gaussians)."""
    score = contribution(params, dataset, seed=seed, backend=backend)
    if kept >= len(score):
        return
    keep = np.zeros(len(score), bool)
    keep[np.argsort(score, kind="stable")[len(score) - kept:]] = True
    keep_gaussians(params, optimizer, torch.from_numpy(keep))


def _psnr(model: Model, views) -> float:
    return psnr_of_mse(mse(render_views(model, views), views.references))


def compress_finetuned(model: Model, dataset, steps: int, preset: str = "web", prune: float = 0.3,
                       seed: int = 0, quantised_steps: int = 0, stages: int = PRUNE_STAGES,
                       still: float = 0.0) -> tuple[Model, Settings, FinetuneInfo]:
    """Fine-tune `steps` steps while pruning the `prune` fraction (0-1) of least important Gaussians
    in `stages` (prune_schedule) and holding still Gaussians with `still` (finetune), and compress with
    `preset` within what is left of its PSNR loss (see the module doc). With `quantised_steps`, then
    fine-tune that many steps through fake quantisation at QAT_LOWER options below the bits chosen
    and search again (_requantised).
    Returns the compressed model, its Settings and a FinetuneInfo."""
    import time

    if preset not in PRESETS or preset == "lossless":
        raise ValueError(f"fine-tuning takes a lossy preset, not {preset!r}")
    if not 0.0 <= prune < 1.0:
        raise ValueError(f"prune must be in [0, 1), got {prune}")
    if not still >= 0.0:
        raise ValueError(f"still must be >= 0, got {still}")
    _check(model, dataset)
    views = dataset_views(dataset, model, VIEW_FRAMES)
    pruned = finetune(model, dataset, 0, seed, prune=prune)
    start = time.perf_counter()
    tuned = finetune(model, dataset, steps, seed, prune=prune, stages=stages, still=still)
    info = FinetuneInfo(model.segments[0].count, tuned.segments[0].count, int(steps), time.perf_counter() - start,
                        _psnr(model, views), _psnr(pruned, views), _psnr(tuned, views),
                        still=_still_count(tuned.segments[0]) if still > 0 else 0)
    left = _loss_left(PRESETS[preset].max_loss_db, info.psnr_original, info.psnr_finetuned)
    out, settings = compress(tuned, preset, views=views, max_loss_db=left)
    if quantised_steps > 0:
        out, settings = _requantised(out, settings, dataset, views, quantised_steps, preset, seed + 1, info)
    return out, settings, info


def _still_count(segment: Segment) -> int:
    """How many Gaussians of `segment` have no motion and no rotation velocity at all."""
    moving = np.any(segment.position[:, 1:] != 0, axis=(1, 2)) | np.any(segment.rotation[:, 1:] != 0, axis=(1, 2))
    return int(np.sum(~moving))


def _loss_left(loss: float, psnr_original: float, psnr: float) -> float:
    """The PSNR loss (dB) a search may still spend on a model of `psnr` so that the file stays within
    `loss` of `psnr_original`: less where the model is below the original, more where above."""
    return max(0.0, loss - (psnr_original - psnr))


def _file_bytes(model: Model, settings: Settings) -> int:
    return len(stg_format.dumps(model, **settings.save_kwargs()))


def _requantised(out: Model, settings: Settings, dataset, views, steps: int, preset: str, seed: int,
                 info: FinetuneInfo) -> tuple[Model, Settings]:
    """Quantisation-aware fine-tuning of the compressed `out` (its Gaussians, order and `settings.bits`
    QAT_LOWER options lower; finetune_quantised, `steps` steps), then the preset's search again on
    the quantised values without further pruning, within what is left of the preset's loss (held-out
    views against info.psnr_original). Returns the smaller of the two within the loss (else the one
    with the higher PSNR); info records the quantised model's PSNR, both (bytes, PSNR) and which one
    was kept."""
    import time

    start = time.perf_counter()
    bits = {name: lowered(b, QAT_LOWER) for name, b in settings.bits.items()}
    qat = finetune_quantised(out, dataset, steps, bits, seed)
    info.quantised_steps, info.psnr_quantised = int(steps), _psnr(qat, views)
    loss = PRESETS[preset].max_loss_db
    left = _loss_left(loss, info.psnr_original, info.psnr_quantised)
    again, again_settings = compress(qat, preset, views=views, max_loss_db=left, prune_opacity=None,
                                     prune_unseen=False, prune_importance=False)
    info.seconds += time.perf_counter() - start
    candidates = []
    for m, s in ((out, settings), (again, again_settings)):
        size, psnr = _file_bytes(m, s), _psnr(m, views)
        info.candidates.append((size, psnr))
        loss_db = info.psnr_original - psnr
        candidates.append((loss_db > loss, size if loss_db <= loss else loss_db, m, s))
    best = min(range(2), key=lambda i: candidates[i][:2])
    info.quantised_kept = best == 1
    return candidates[best][2], candidates[best][3]


def finetune_file(in_path, out_path, dataset, steps: int, preset: str = "web", prune: float = 0.3,
                  seed: int = 0, quantised_steps: int = 0, stages: int = PRUNE_STAGES,
                  still: float = 0.0) -> tuple[Report, FinetuneInfo]:
    """Read `in_path`, compress_finetuned it against `dataset`, write `out_path` atomically; the report
    compares with the input file. ValueError (the file named) for a model fine-tuning cannot take."""
    model = stg_format.load(in_path)
    try:
        compressed, settings, info = compress_finetuned(model, dataset, steps, preset, prune, seed,
                                                        quantised_steps, stages, still)
    except ValueError as e:
        raise ValueError(f"{os.fsdecode(in_path)}: {e}") from None
    compressed.provenance["compress"]["finetune"] = {"steps": int(steps), "prune": float(prune), "seed": int(seed),
                                                       "quantised_steps": int(quantised_steps), "stages": int(stages),
                                                       "still": float(still)}
    rep = report(model, compressed, settings, dataset_views(dataset, model, VIEW_FRAMES),
                 file_attribute_bytes(in_path), os.path.getsize(in_path))
    stg_format.save(compressed, out_path, **settings.save_kwargs())
    rep.file_after = os.path.getsize(out_path)
    return rep, info
