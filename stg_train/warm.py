"""Warm-started segments: segment k+1 of a long video begins from segment k's Gaussians.

A segment's time is normalised over its own frames (stg_train.segments: frame j of a segment of n
frames has tau = j / n). Video frame f is tau_k = (f - s_k) / n_k on segment k's axis and
tau_{k+1} = (f - s_{k+1}) / n_{k+1} on the next one's, so tau_{k+1} = a tau_k + b with a = n_k / n_{k+1},
b = (s_k - s_{k+1}) / n_{k+1} (an affine map; -1 for consecutive 50-frame segments). rebase_time
re-expresses raw parameters on the new axis exactly: the Gaussians render the same picture at every
video frame (only float rounding differs). Gaussians whose temporal opacity never reaches the
pruning threshold inside the new segment's frames (context included) are dropped (past_gaussians);
static Gaussians (time terms frozen) are carried unchanged. Features and the decoder's weights carry
over as they are; Adam's moments and the strategies' statistics start afresh.

    rebase_time(raw, a, b)                the raw parameters on the axis tau' = a tau + b
    axis_map(prev, span)                  (a, b) from one Span's axis to the next's
    past_gaussians(raw, lo, hi, floor)    (N,) bool: no opacity above floor for tau in [lo, hi]
    extend_at_seam(raw, scale, floor)     the Gaussians drawn at the seam made to last into the segment
    WarmStart, warm_start(...)            what a warm segment starts from (read from a checkpoint)
    warm_steps(iterations, fraction)      a warm segment's iterations
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from .checkpoint import CheckpointError, read_checkpoint
from .params import STGParams, temporal_opacity
from .segments import SegmentError, Span

#: A warm segment drops the carried Gaussians whose opacity stays below this over its frames (the
#: density control's pruning threshold, strategy.density.Thresholds.prune_opacity).
PAST_OPACITY = 0.005


def axis_map(prev: Span, span: Span) -> tuple[float, float]:
    """(a, b) with tau_span = a tau_prev + b for every video frame: a = prev.count / span.count,
    b = (prev.start - span.start) / span.count."""
    return prev.count / span.count, (prev.start - span.start) / span.count


def rebase_time(raw: dict[str, Tensor], a: float, b: float, frozen=()) -> dict[str, Tensor]:
    """Raw parameters (stg_train.params's names) re-expressed on the time axis tau' = a tau + b (a > 0)
    so that they evaluate to the same Gaussians at every instant: t_center' = a t_center + b, the
    temporal scale times a (t_scale_raw + log a), the polynomial motion's degree-d coefficients / a^d,
    the rotation velocity and the time features / a (they multiply dt = dt' / a). Everything else, and
    the parameters of `frozen` components (params.COMPONENTS: kept at their initial values, e.g. a
    static model's), unchanged. Returns new tensors (same dtype and device); a float64 input stays exact."""
    if not a > 0:
        raise ValueError(f"rebase_time: the axis scale a must be positive, got {a}")
    from .params import COMPONENTS

    keep = {name for c in frozen for name in COMPONENTS[c]}
    out = {k: v.detach().clone() for k, v in raw.items()}
    if "t_center" not in keep:
        out["t_center"] = raw["t_center"].detach() * a + b
    if "t_scale_raw" not in keep:
        out["t_scale_raw"] = raw["t_scale_raw"].detach() + math.log(a)
    if "motion" not in keep:
        m = raw["motion"].detach()
        out["motion"] = torch.cat([m[:, 0:3] / a, m[:, 3:6] / a ** 2, m[:, 6:9] / a ** 3], dim=1)
    if "omega" not in keep:
        out["omega"] = raw["omega"].detach() / a
    if raw.get("time_features") is not None and "time_features" not in keep:
        out["time_features"] = raw["time_features"].detach() / a
    return out


def past_gaussians(raw: dict[str, Tensor], lo: float, hi: float, floor: float = PAST_OPACITY) -> Tensor:
    """(N,) bool: the Gaussians whose opacity sigmoid(opacity_logit) exp(-((tau - t_center) / s)^2)
    stays below `floor` for every tau in [lo, hi] (its largest value there is at the clamp of t_center
    into [lo, hi])."""
    raw = {k: raw[k].detach() for k in ("opacity_logit", "t_center", "t_scale_raw")}
    return temporal_opacity(raw, raw["t_center"].reshape(-1).clamp(lo, hi)) < floor


def extend_at_seam(raw: dict[str, Tensor], scale: float, floor: float = PAST_OPACITY,
                   frozen=()) -> dict[str, Tensor]:
    """Raw parameters on the new segment's axis (rebase_time's) with the Gaussians drawn at its first
    frame (temporal opacity at tau = 0 at least `floor`) made to last into the segment, keeping that
    frame's picture: their temporal scale s raised to at least `scale` (s' = max(s, scale)) with the
    spatial opacity lowered so that the opacity at tau = 0 is unchanged (sigmoid(o') = sigmoid(o)
    exp((dt0 / s')^2 - (dt0 / s)^2), dt0 = -t_center), and their cubic motion replaced by the line with
    the same position and velocity at tau = 0 (a cubic fitted over the segment before runs away when
    it is extended past its end; kept when "motion" is in `frozen`). The caller skips models whose
    temporal opacity is frozen. scale <= 0: unchanged. Returns new tensors."""
    out = {k: v.detach().clone() for k, v in raw.items()}
    if scale <= 0:
        return out
    dt0 = -out["t_center"].reshape(-1)
    s = torch.exp(out["t_scale_raw"].reshape(-1))
    alive = temporal_opacity(out, 0.0) >= floor
    widen = alive & (s < scale)
    s_new = torch.where(widen, torch.full_like(s, scale), s)
    o = torch.sigmoid(out["opacity_logit"].reshape(-1)) * torch.exp((dt0 / s_new) ** 2 - (dt0 / s) ** 2)
    o = o.clamp(1e-7, 1 - 1e-7)
    t_raw = out["t_scale_raw"].reshape(-1)
    out["t_scale_raw"] = torch.where(widen, torch.full_like(t_raw, math.log(scale)), t_raw).reshape(
        out["t_scale_raw"].shape)
    out["opacity_logit"] = torch.where(widen, torch.logit(o), out["opacity_logit"].reshape(-1)).reshape(
        out["opacity_logit"].shape)
    if "motion" in frozen:
        return out
    m, d = out["motion"], dt0[:, None]
    at_seam = d * (m[:, 0:3] + d * (m[:, 3:6] + d * m[:, 6:9]))
    velocity = m[:, 0:3] + d * (2 * m[:, 3:6] + 3 * d * m[:, 6:9])
    line = widen[:, None]
    out["xyz"] = torch.where(line, out["xyz"] + at_seam - d * velocity, out["xyz"])
    out["motion"] = torch.where(line, torch.cat([velocity, torch.zeros_like(m[:, 3:9])], dim=1), m)
    return out


class WarmStart(NamedTuple):
    """What a warm segment starts from: params (STGParams on the new axis), box (2, 3) the first
    segment's initial points' bounds, bounds (near / far per camera, or None) and bounds_source as the
    previous segment had them, carried (the Gaussians carried), dropped (those past_gaussians removed)."""

    params: STGParams
    box: np.ndarray
    bounds: np.ndarray | None
    bounds_source: str | None
    carried: int
    dropped: int


def warm_start(checkpoint: Path, prev: Span, span: Span, context: tuple[int, int], device="cpu",
               time_scale: float = 0.0) -> WarmStart:
    """The start of segment `span` from the checkpoint of the segment `prev` before it (a finished
    run's OUT/segments/NN/checkpoint.pt): its parameters rebased onto span's axis (rebase_time,
    axis_map), those past the new segment's frames and its `context` (before, after) frames dropped
    (past_gaussians over tau in [-before / n, 1 + after / n]), and those drawn at its first frame made
    to last at least `time_scale` (extend_at_seam; not for a static model). Raises SegmentError for an
    unreadable checkpoint (naming it)."""
    try:
        state = read_checkpoint(checkpoint)
    except CheckpointError as e:
        raise SegmentError(f"{e}: the next segment's warm start needs it (retrain that segment, or use "
                           "--segment-schedule independent)") from None
    saved = state["params"]
    a, b = axis_map(prev, span)
    raw = rebase_time(saved["raw"], a, b, saved.get("frozen", ()))
    before, after = context
    past = past_gaussians(raw, -before / span.count, 1 + after / span.count)
    if saved.get("static"):
        past[:] = False
    raw = {k: v[~past] for k, v in raw.items()}
    if not saved.get("static") and "temporal_opacity" not in saved.get("frozen", ()):
        raw = extend_at_seam(raw, time_scale, frozen=saved.get("frozen", ()))
    params = STGParams.from_state_dict({**saved, "raw": raw}, device)
    bounds = state.get("bounds")
    return WarmStart(params, np.asarray(state["box"]), None if bounds is None else np.asarray(bounds),
                     state.get("bounds_source"), params.count, int(past.sum()))


def warm_steps(iterations: int, fraction: float) -> int:
    """A warm segment's iterations: `fraction` of a cold segment's `iterations` (at least 1)."""
    return max(1, round(iterations * fraction))


def chain_head(index: int, chain: int = 0) -> bool:
    """Whether segment `index` starts cold in a warm schedule: the first, and with chain > 0 every
    chain-th (parallel chains of `chain` segments; 0: one chain)."""
    return index == 0 or (chain > 0 and index % chain == 0)


def start_of(out: Path, plan: list[Span], index: int, config, device="cpu") -> WarmStart | None:
    """How segment `index` of `plan` (trained into out/segments/NN) starts under config.segment_schedule:
    a WarmStart from its predecessor's checkpoint, or None (cold: its own initial points) for an
    independent schedule, a chain head (chain_head, config.warm_chain) or a predecessor that is not
    finished with its checkpoint in its folder (trained elsewhere, or not yet)."""
    from .segments import context_of, finished, segment_dir

    if config.segment_schedule != "warm" or chain_head(index, config.warm_chain):
        return None
    prev = segment_dir(out, index - 1, len(plan))
    if not finished(prev, plan[index - 1]) or not (prev / "checkpoint.pt").exists():
        return None
    num_frames = plan[-1].start + plan[-1].count
    return warm_start(prev / "checkpoint.pt", plan[index - 1], plan[index],
                      context_of(plan[index], num_frames, config.segment_context), device,
                      config.warm_time_scale)
