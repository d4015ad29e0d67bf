"""Density control (clone / split / prune / opacity reset), the reference implementation's, as a strategy.

Thresholds and schedule follow the reference implementation (N3V settings, 30k iterations): densify
from 500 every 100 iterations for 6 rounds (gradient threshold 2e-4 in NDC units, percent_dense 0.01,
split into 2 with scale / 1.6, cloned and split Gaussians get a random temporal centre; ours centres
them at a time where their parent was hot, Thresholds.new_t_center), prune opacity
< 0.005 every 100 iterations until 7k, opacity reset to <= 0.01 every 3000 until 9k, Gaussians outside
the initial box removed at 10k. Schedule.scaled(total) maps these onto a run of `total` iterations.
The gradient statistic is gsplat's (per view, independent of the batch size; the reference's, one
view per backward, has the same mean); docs/training.md has the deviations from the reference and
their measurements.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch
from torch import Tensor

from ..params import STGParams
from ..render.torch_splat import quat_to_rotmat
from .base import StepContext, Strategy
from .ops import append_gaussians, keep_gaussians, set_values
from .schedule import Schedule


#: Thresholds.grad_statistic values.
GRAD_STATISTICS = ("per-view", "summed")
#: Thresholds.new_t_center values.
NEW_T_CENTERS = ("gradient", "sampled", "random", "parent")


@dataclass(frozen=True)
class Thresholds:
    """The reference implementation's thresholds (3DGS's, N3V settings)."""

    grad: float = 2e-4  # mean screen-space gradient norm (NDC units) that triggers densification
    percent_dense: float = 0.01  # clone below, split above this max scale (x scene extent)
    split_scale: float = 1.6  # split children's scale = parent / split_scale
    prune_opacity: float = 0.005
    max_screen_radius: float = 20.0  # pixels; pruned when bigger, after the first opacity reset
    max_world_scale: float = 0.1  # x extent; pruned when bigger, after the first opacity reset
    reset_opacity: float = 0.01
    # the temporal centre of cloned and split Gaussians, where in time their parent was hot, over the
    # steps since the last densification: "sampled" (one of those steps' times, drawn with probability
    # in proportion to the parent's screen gradient there, a weighted reservoir sample), "gradient"
    # (their mean, weighted the same way; the default before 2026-12-04: a parent hot at two times sent
    # its copies between them, and the mean of a long-lived parent's hot times lies near the middle of
    # the clip, which left a segment's edges with few short-lived Gaussians), "random" (uniform in
    # [0, 1), the reference's; `recentre` below) or "parent" (the parent's centre). With "sampled" and
    # "gradient" the new Gaussians' motion is re-expanded about their new centre, so that they keep the
    # parent's trajectory
    new_t_center: str = "sampled"
    # a step counts in a Gaussian's mean gradient only when its temporal opacity factor
    # exp(-(dt / s_t)^2) at the step's time is above this (0: every step it is on screen, the reference)
    min_temporal_opacity: float = 0.0
    # with new_t_center "random": re-expand the new Gaussians' motion and rotation about their new
    # temporal centre, so that they keep their parent's trajectory (False: xyz and the coefficients stay,
    # which shifts the trajectory in time by the change of centre, as the reference does)
    recentre: bool = False
    # the densification statistic (DensityControl.accumulate): "per-view" (gsplat's default strategy:
    # each view's gradient norm, the loss's 1 / B undone, averaged over the views that see the Gaussian;
    # the same at every batch size) or "summed" (before 2026-12: the batch's gradient vectors summed,
    # then normed, once per step; up to B times stricter; kept for ablations)
    grad_statistic: str = "per-view"
    # densification steps also prune (low opacity, and after the first reset too big); False: they only
    # clone and split, as the reference's densify_pruneclone (which builds its prune mask and never
    # applies it); the separate prune steps act either way
    prune_at_densify: bool = True

    def __post_init__(self):
        if self.grad_statistic not in GRAD_STATISTICS:
            raise ValueError(f"grad_statistic must be one of {GRAD_STATISTICS}, got {self.grad_statistic!r}")
        if self.new_t_center not in NEW_T_CENTERS:
            raise ValueError(f"new_t_center must be one of {NEW_T_CENTERS}, got {self.new_t_center!r}")


def recentred(raw: dict[str, Tensor], t_center: Tensor) -> dict[str, Tensor]:
    """xyz, motion, rotation of Gaussians `raw` (stg_train.raw's names) expanded about new temporal
    centres t_center (K, 1) so that position(t) and the unnormalised rotation(t) stay the same
    functions of t: with d = new - old centre, the cubic x + a dt + b dt^2 + c dt^3 becomes
    (x + a d + b d^2 + c d^3) + (a + 2 b d + 3 c d^2) dt' + (b + 3 c d) dt'^2 + c dt'^3, and q + omega dt
    becomes (q + omega d) + omega dt'. (The time features, dt x f, cannot be re-expanded and stay.)"""
    d = t_center - raw["t_center"]
    a, b, c = raw["motion"][:, 0:3], raw["motion"][:, 3:6], raw["motion"][:, 6:9]
    return {"xyz": raw["xyz"] + d * (a + d * (b + d * c)),
            "motion": torch.cat([a + d * (2 * b + 3 * d * c), b + 3 * d * c, c], dim=1),
            "rotation": raw["rotation"] + d * raw["omega"]}


class DensityControl(Strategy):
    """Clone / split / prune / opacity reset on `schedule` with `thresholds`.

    extent: the scene extent (world units) that percent_dense and max_world_scale multiply;
    box: (min (3,), max (3,)) of the initial points, for the "outside the box" removal (None: never).
    The random temporal centres and split offsets come from torch's global generator (checkpointed by
    the trainer).
    """

    def __init__(self, schedule: Schedule, extent: float, thresholds: Thresholds = Thresholds(), box=None):
        self.schedule, self.thresholds, self.extent = schedule, thresholds, float(extent)
        self.box = None if box is None else torch.as_tensor(box, dtype=torch.float32).reshape(2, 3)
        self.grad_sum = torch.zeros(0)  # (N,) sum of NDC gradient norms (Thresholds.grad_statistic)
        self.grad_count = torch.zeros(0)  # (N,) views (per-view) or steps (summed) that saw the Gaussian
        self.grad_time = torch.zeros(0)  # (N,) the same gradient norms times their step's normalised time
        self.hot_sample = torch.zeros(0)  # (N,) one step's normalised time, drawn in proportion to its norm
        # (NaN until a step adds a norm)
        self.max_radius = torch.zeros(0)  # (N,) largest screen radius (pixels) since the last refine
        self.rounds_done = 0
        self.log: list[dict] = []  # one entry per refine step (counts), for reports

    # -- statistics ------------------------------------------------------------------------------------
    def _fit(self, n: int) -> None:
        """Extend the statistics with zeros for Gaussians appended by other strategies."""
        short = n - self.grad_sum.shape[0]
        if short > 0:
            self.grad_sum = torch.cat([self.grad_sum, torch.zeros(short)])
            self.grad_count = torch.cat([self.grad_count, torch.zeros(short)])
            self.grad_time = torch.cat([self.grad_time, torch.zeros(short)])
            self.hot_sample = torch.cat([self.hot_sample, torch.full((short,), math.nan)])
            self.max_radius = torch.cat([self.max_radius, torch.zeros(short)])
        elif short < 0:
            raise RuntimeError("DensityControl: Gaussians were removed outside DensityControl")

    def accumulate(self, renders: list, tau: float, present=None) -> None:
        """Add one step's statistics. renders: (camera, splat.RenderOutput) for every view of the batch;
        tau: the step's normalised time (each norm added is also added times tau, and may replace the
        Gaussian's sampled time, for new_t_center "gradient" and "sampled"); present: optional (N,)
        bool on the CPU, the Gaussians that exist at the step's time (others do not count).

        Screen gradients are converted from pixels to NDC units (x W/2, H/2). With grad_statistic
        "per-view" (gsplat's default strategy) each view's gradient is multiplied by the number of views
        B, which undoes the loss's mean over the batch, then normed; the norm is added, and the count
        raised, for every view that sees the Gaussian. A Gaussian that every view sees with the same
        full-size-loss gradient g then averages |g| at any batch size, as the reference's statistic
        (one backward per view, the last view's |g|) does. "summed": the views' gradient vectors are
        added first and normed once per step (the old statistic; see Thresholds)."""
        views = [(camera, out) for camera, out in renders if out.means2d.grad is not None]
        if not views:
            return
        per_view = self.thresholds.grad_statistic == "per-view"
        summed, seen_any = None, None
        for camera, out in views:
            scale = torch.tensor([camera.width / 2.0, camera.height / 2.0]) * (len(renders) if per_view else 1)
            g = out.means2d.grad.detach().cpu().reshape(-1, 2) * scale  # px -> NDC
            seen = out.visible.detach().cpu()
            self._fit(g.shape[0])
            if present is not None:
                seen = seen & present
            r = out.radii.detach().cpu().float()
            # dense updates (zero where unseen) rather than masked ones: the same sums, several times faster
            self.max_radius = torch.where(seen, torch.maximum(self.max_radius, r), self.max_radius)
            if per_view:
                self._add(torch.where(seen, g.norm(dim=-1), 0.0), seen, tau)
            else:
                summed = g if summed is None else summed + g
                seen_any = seen if seen_any is None else seen_any | seen
        if not per_view:
            self._add(torch.where(seen_any, summed.norm(dim=-1), 0.0), seen_any, tau)

    def _add(self, norm: Tensor, seen: Tensor, tau: float) -> None:
        """Add gradient norms (N,) (0 where not seen), counted where `seen` (N,) bool, at time tau."""
        self.grad_sum += norm
        self.grad_time += norm * tau
        self.grad_count += seen
        if self.thresholds.new_t_center == "sampled":  # replace the sample with probability norm / sum
            take = torch.rand(norm.shape[0]) * self.grad_sum < norm
            self.hot_sample = torch.where(take, tau, self.hot_sample)

    # -- the plug-in entry point ------------------------------------------------------------------------
    def step_post_backward(self, params: STGParams, optimizer: torch.optim.Optimizer, step: int,
                           context: StepContext) -> None:
        """Accumulate the step's screen gradients; on the schedule, densify, prune, reset or cull."""
        s = self.schedule
        self._fit(params.count)
        if step <= s.prune_until or self.rounds_done < s.densify_rounds:
            self.accumulate(context.renders, context.tau, self._present(params, context.tau))
        if step > s.refine_start and step % s.refine_every == 0:
            if self.rounds_done < s.densify_rounds:
                self.densify_and_prune(params, optimizer, step)
                self.rounds_done += 1
            elif step <= s.prune_until:
                self.prune(params, optimizer, step)
        if s.reset_every and step % s.reset_every == 0 and step <= s.reset_until:
            self.reset_opacity(params, optimizer)
        if s.outside_at and step == s.outside_at and self.box is not None:
            xyz = params["xyz"].detach().cpu()
            inside = ((xyz >= self.box[0]) & (xyz <= self.box[1])).all(1)
            self._keep(params, optimizer, inside.to(params.device))

    def _present(self, params: STGParams, tau: float) -> Tensor | None:
        """(N,) bool on the CPU: temporal opacity factor at tau above thresholds.min_temporal_opacity
        (None when that is 0: every Gaussian counts)."""
        if self.thresholds.min_temporal_opacity <= 0:
            return None
        with torch.no_grad():
            dt = tau - params["t_center"].detach().reshape(-1)
            factor = torch.exp(-(dt / torch.exp(params["t_scale_raw"].detach().reshape(-1))) ** 2)
        return (factor > self.thresholds.min_temporal_opacity).cpu()

    # -- operations ------------------------------------------------------------------------------------
    def _keep(self, params, optimizer, keep: Tensor) -> None:
        keep_cpu = keep.cpu()
        keep_gaussians(params, optimizer, keep)
        self.grad_sum, self.grad_count = self.grad_sum[keep_cpu], self.grad_count[keep_cpu]
        self.grad_time, self.hot_sample = self.grad_time[keep_cpu], self.hot_sample[keep_cpu]
        self.max_radius = self.max_radius[keep_cpu]

    def _reset_stats(self, n: int) -> None:
        self.grad_sum, self.grad_count, self.max_radius = torch.zeros(n), torch.zeros(n), torch.zeros(n)
        self.grad_time, self.hot_sample = torch.zeros(n), torch.full((n,), math.nan)

    def _prune_mask(self, params: STGParams, step: int, big: bool) -> Tensor:
        """(N,) bool on the CPU: Gaussians to remove: low opacity, and with `big` after the first opacity
        reset also too big on screen or in the world (as the reference's densification step)."""
        th = self.thresholds
        opacity = torch.sigmoid(params["opacity_logit"].detach().cpu()).reshape(-1)
        prune = opacity < th.prune_opacity
        if big and self.schedule.reset_every and step > self.schedule.reset_every:
            scale = torch.exp(params["log_scale"].detach().cpu()).amax(1)
            prune |= self.max_radius > th.max_screen_radius
            prune |= scale > th.max_world_scale * self.extent
        return prune

    def prune(self, params: STGParams, optimizer, step: int) -> None:
        """Remove Gaussians with opacity below the threshold."""
        prune = self._prune_mask(params, step, big=False)
        self._keep(params, optimizer, (~prune).to(params.device))
        self._reset_stats(params.count)
        self.log.append({"step": step, "pruned": int(prune.sum()), "count": params.count})

    def densify_and_prune(self, params: STGParams, optimizer, step: int) -> None:
        """Clone small and split big Gaussians whose mean gradient exceeds the threshold, then prune."""
        th, dev, n = self.thresholds, params.device, params.count
        mean_grad = self.grad_sum / self.grad_count.clamp_min(1)
        hot = mean_grad >= th.grad
        max_scale = torch.exp(params["log_scale"].detach().cpu()).amax(1)
        small = max_scale <= th.percent_dense * self.extent
        clone, split = hot & small, hot & ~small

        raw = {k: v.detach() for k, v in params.raw.items()}
        new = {k: v[clone.to(dev)] for k, v in raw.items()}
        # split: two children sampled from the parent Gaussian, scale / split_scale; the parent goes
        idx = torch.nonzero(split).squeeze(1).to(dev)
        if idx.numel():
            stds = torch.exp(raw["log_scale"][idx]).repeat(2, 1)
            offsets = torch.randn(stds.shape, generator=None).to(dev) * stds
            rot = quat_to_rotmat(raw["rotation"][idx]).repeat(2, 1, 1)
            children = {k: v[idx].repeat(2, *([1] * (v.dim() - 1))) for k, v in raw.items()}
            children["xyz"] = children["xyz"] + (rot @ offsets[..., None]).squeeze(-1)
            children["log_scale"] = children["log_scale"] - math.log(th.split_scale)
            new = {k: torch.cat([new[k], children[k]]) for k in raw}
        if th.new_t_center != "parent" and next(iter(new.values())).shape[0]:
            parents = torch.nonzero(clone).squeeze(1)
            new = self._centred_in_time(new, torch.cat([parents, idx.cpu(), idx.cpu()]))
        append_gaussians(params, optimizer, new)
        self._fit(params.count)  # the new Gaussians have no statistics yet
        prune = (self._prune_mask(params, step, big=True) if th.prune_at_densify
                 else torch.zeros(params.count, dtype=torch.bool))
        prune[:n] |= split  # split parents go
        self._keep(params, optimizer, (~prune).to(dev))
        self._reset_stats(params.count)
        self.log.append({"step": step, "cloned": int(clone.sum()), "split": int(split.sum()),
                         "pruned": int(prune.sum()) - int(split.sum()), "count": params.count})

    def _centred_in_time(self, new: dict[str, Tensor], parents: Tensor) -> dict[str, Tensor]:
        """The new Gaussians `new` (raw rows; row k a copy of Gaussian parents[k], (K,) indices into the
        statistics) with their temporal centres set by thresholds.new_t_center, "gradient", "sampled" or
        "random".
        A parent whose hot time is unknown (a checkpoint from before it was kept) passes on its own."""
        th = self.thresholds
        if th.new_t_center == "random":
            t_center = torch.rand(parents.shape[0], 1).to(new["t_center"].device)
            return {**new, **(recentred(new, t_center) if th.recentre else {}), "t_center": t_center}
        hot_time = self.hot_sample[parents] if th.new_t_center == "sampled" else \
            self.grad_time[parents] / self.grad_sum[parents]
        hot_time = hot_time.reshape(-1, 1).to(new["t_center"].device)
        t_center = torch.where(torch.isfinite(hot_time), hot_time, new["t_center"])
        return {**new, **recentred(new, t_center), "t_center": t_center}

    def reset_opacity(self, params: STGParams, optimizer) -> None:
        """opacity = min(opacity, reset_opacity) (in logit space), Adam moments of opacity zeroed."""
        cap = math.log(self.thresholds.reset_opacity / (1 - self.thresholds.reset_opacity))
        set_values(params, optimizer, "opacity_logit", params["opacity_logit"].detach().clamp(max=cap))

    # -- checkpoints -----------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {"grad_sum": self.grad_sum.clone(), "grad_count": self.grad_count.clone(),
                "grad_time": self.grad_time.clone(), "hot_sample": self.hot_sample.clone(),
                "max_radius": self.max_radius.clone(), "rounds_done": self.rounds_done, "log": list(self.log),
                "schedule": asdict(self.schedule), "thresholds": asdict(self.thresholds), "extent": self.extent}

    def load_state_dict(self, state: dict) -> None:
        self.grad_sum, self.grad_count = state["grad_sum"].clone(), state["grad_count"].clone()
        # a checkpoint from before the hot times were kept: the next round's parents pass on their centres
        self.grad_time = state.get("grad_time", torch.full_like(self.grad_sum, math.nan)).clone()
        self.hot_sample = state.get("hot_sample", torch.full_like(self.grad_sum, math.nan)).clone()
        self.max_radius = state["max_radius"].clone()
        self.rounds_done, self.log = int(state["rounds_done"]), list(state["log"])
