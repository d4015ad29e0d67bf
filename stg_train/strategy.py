"""Density control (clone / split / prune / opacity reset) as a plug-in called after backward.

The idea is gsplat's `Strategy`: the trainer calls `strategy.step_post_backward(params, optimizer,
renders, step)` once per iteration after `loss.backward()` and before `optimizer.step()`; the strategy
reads the screen-space gradients of the renders, and on its schedule edits the Gaussians through
`append_gaussians` / `keep_gaussians`, which keep the Adam state of every parameter tensor in step.

Other strategies (e.g. guided sampling, stg_train.guided) plug in the same way: an object with
`step_post_backward(params, optimizer, renders, step)`, `state_dict()` and `load_state_dict(state)`,
placed in the trainer's list of strategies after `DensityControl`. They may add Gaussians with
`append_gaussians` (new rows go at the end; `DensityControl` extends its statistics with zeros for them)
and must leave removing them to `DensityControl`. A strategy that needs more than the batch's renders
(ground truth, renders of other training views) sets the class attribute `wants_context = True`; the
trainer then calls `step_post_backward(params, optimizer, renders, step, context=StepContext(...))`
with the dataset, the step's frame and time, and functions that render a training view and fetch its
ground truth. Random numbers must come from torch's global generator (checkpointed by the trainer), so
that a resumed run reaches the same state.

Thresholds and schedule follow the reference implementation (N3V settings, 30k iterations): densify
from 500 every 100 iterations for 6 rounds (gradient threshold 2e-4 in NDC units, percent_dense 0.01,
split into 2 with scale / 1.6, cloned and split Gaussians get a random temporal centre), prune opacity
< 0.005 every 100 iterations until 7k, opacity reset to <= 0.01 every 3000 until 9k, Gaussians outside
the initial box removed at 10k. `Schedule.scaled(total)` maps these onto a run of `total` iterations.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace
from typing import Callable, NamedTuple

import torch
from torch import Tensor

from .params import STGParams
from .splat import quat_to_rotmat


@dataclass(frozen=True)
class Schedule:
    """When density control acts (iteration numbers of the run it is used in)."""

    refine_start: int = 500  # first densify / prune step (exclusive, as the reference: it > start)
    refine_every: int = 100
    densify_rounds: int = 6  # densification steps; later refine steps only prune
    prune_until: int = 7000
    reset_every: int = 3000  # opacity reset period; 0 disables
    reset_until: int = 9000
    outside_at: int = 10000  # remove Gaussians outside the initial box at this step; 0 disables
    guided_start: int = 1600  # guided sampling (stg_train.guided): views chosen at this step, first sampling
    guided_every: int = 100  # steps between guided samplings (one per chosen view)

    @classmethod
    def scaled(cls, total: int, reference_total: int = 30000, min_every: int = 25, min_start: int = 50,
               min_reset_every: int = 1000, **overrides) -> "Schedule":
        """The reference schedule (for `reference_total` iterations) stretched to `total` iterations.

        Floors keep short runs sensible (measured on the synthetic scenes): at least `min_every` steps of
        gradient statistics per refine step, the first after `min_start` steps, and opacity resets at
        least `min_reset_every` steps apart (opacity needs that long to recover; runs shorter than
        about 3x that have none). Guided sampling starts where the reference's does relative to density
        control (its 1600 = refine_start + (densify_rounds + 5) refine periods, after the densification
        rounds, once the loss is stable), or at the scaled 1600 if later; its samplings are a refine
        period apart. A 30k-iteration run gets exactly the reference schedule. Keyword overrides
        replace single fields (they do not move the other fields)."""
        f = total / reference_total
        ref = cls()
        start = max(min_start, round(ref.refine_start * f))
        every = max(min_every, round(ref.refine_every * f))
        sched = cls(refine_start=start, refine_every=every,
                    densify_rounds=ref.densify_rounds,
                    prune_until=round(ref.prune_until * f),
                    reset_every=max(min_reset_every, round(ref.reset_every * f)),
                    reset_until=round(ref.reset_until * f),
                    outside_at=round(ref.outside_at * f),
                    guided_start=max(round(ref.guided_start * f), start + (ref.densify_rounds + 5) * every),
                    guided_every=max(min_every, round(ref.guided_every * f)))
        return replace(sched, **overrides)


class StepContext(NamedTuple):
    """What the trainer passes to strategies with `wants_context = True` (see the module docstring).

    dataset: the stg_train.data.Dataset; frame: the step's frame index; tau: its normalised time;
    render(camera_index, tau) -> (rgb (H, W, 3), splat.RenderOutput) of the current parameters (call it
    under torch.no_grad()); ground_truth(camera_index, frame) -> (H, W, 3) float in [0, 1] on the device.
    """

    dataset: object
    frame: int
    tau: float
    render: Callable
    ground_truth: Callable


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
    random_t_center: bool = True  # cloned / split Gaussians get a uniform random temporal centre


# -- editing Gaussians with the optimizer in step -------------------------------------------------------
def _swap(params: STGParams, optimizer: torch.optim.Optimizer, name: str, new_value: Tensor, edit_state) -> None:
    """Replace raw parameter `name` by new_value (a fresh leaf), editing its Adam moments with edit_state."""
    old = params.raw[name]
    new = new_value.detach().contiguous().requires_grad_(old.requires_grad)
    params.raw[name] = new
    for group in optimizer.param_groups:
        if group.get("name") == name:
            group["params"][0] = new
            state = optimizer.state.pop(old, None)
            if state:
                for key in ("exp_avg", "exp_avg_sq"):
                    if key in state:
                        state[key] = edit_state(state[key])
                optimizer.state[new] = state
            return


def append_gaussians(params: STGParams, optimizer: torch.optim.Optimizer, new: dict[str, Tensor]) -> None:
    """Add Gaussians at the end: new[name] (K, ...) raw values for every name in params.raw; their Adam
    moments start at zero."""
    k = next(iter(new.values())).shape[0]
    for name, value in params.raw.items():
        extra = new[name].to(value)
        _swap(params, optimizer, name, torch.cat([value.detach(), extra]),
              lambda s, k=k: torch.cat([s, s.new_zeros((k,) + s.shape[1:])]))


def keep_gaussians(params: STGParams, optimizer: torch.optim.Optimizer, keep: Tensor) -> None:
    """Keep only the Gaussians where keep (N,) bool is True (values and Adam moments)."""
    for name, value in params.raw.items():
        _swap(params, optimizer, name, value.detach()[keep], lambda s: s[keep])


def set_values(params: STGParams, optimizer: torch.optim.Optimizer, name: str, value: Tensor) -> None:
    """Overwrite raw parameter `name` and zero its Adam moments (as 3DGS's opacity reset does)."""
    _swap(params, optimizer, name, value, torch.zeros_like)


# -- the strategy --------------------------------------------------------------------------------------
class DensityControl:
    """Clone / split / prune / opacity reset on `schedule` with `thresholds`.

    extent: the scene extent (world units) that percent_dense and max_world_scale multiply;
    box: (min (3,), max (3,)) of the initial points, for the "outside the box" removal (None: never).
    The random temporal centres and split offsets come from torch's global generator (checkpointed by
    the trainer).
    """

    def __init__(self, schedule: Schedule, extent: float, thresholds: Thresholds = Thresholds(), box=None):
        self.schedule, self.thresholds, self.extent = schedule, thresholds, float(extent)
        self.box = None if box is None else torch.as_tensor(box, dtype=torch.float32).reshape(2, 3)
        self.grad_sum = torch.zeros(0)  # (N,) sum of per-step NDC gradient norms
        self.grad_count = torch.zeros(0)  # (N,) steps in which the Gaussian was visible
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
            self.max_radius = torch.cat([self.max_radius, torch.zeros(short)])
        elif short < 0:
            raise RuntimeError("DensityControl: Gaussians were removed outside DensityControl")

    def accumulate(self, renders: list) -> None:
        """Add one step's statistics. renders: (camera, splat.RenderOutput) for every view of the batch;
        the per-view screen gradients are summed (the loss averages the views), then normed."""
        grad, seen, radius = None, None, None
        for camera, out in renders:
            g = out.means2d.grad
            if g is None:
                continue
            g = g.detach().cpu().reshape(-1, 2) * torch.tensor([camera.width / 2.0, camera.height / 2.0])  # px -> NDC
            vis = out.visible.detach().cpu()
            r = out.radii.detach().cpu().float()
            grad = g if grad is None else grad + g
            seen = vis if seen is None else seen | vis
            radius = r if radius is None else torch.maximum(radius, r)
        if grad is None:
            return
        self._fit(grad.shape[0])
        norm = grad.norm(dim=-1)
        self.grad_sum[seen] += norm[seen]
        self.grad_count[seen] += 1
        self.max_radius[seen] = torch.maximum(self.max_radius[seen], radius[seen])

    # -- the plug-in entry point ------------------------------------------------------------------------
    def step_post_backward(self, params: STGParams, optimizer: torch.optim.Optimizer, renders: list,
                           step: int) -> None:
        """Called once per iteration (step counts from 1) after backward, before optimizer.step()."""
        s = self.schedule
        self._fit(params.count)
        if step <= s.prune_until or self.rounds_done < s.densify_rounds:
            self.accumulate(renders)
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

    # -- operations ------------------------------------------------------------------------------------
    def _keep(self, params, optimizer, keep: Tensor) -> None:
        keep_cpu = keep.cpu()
        keep_gaussians(params, optimizer, keep)
        self.grad_sum, self.grad_count = self.grad_sum[keep_cpu], self.grad_count[keep_cpu]
        self.max_radius = self.max_radius[keep_cpu]

    def _reset_stats(self, n: int) -> None:
        self.grad_sum, self.grad_count, self.max_radius = torch.zeros(n), torch.zeros(n), torch.zeros(n)

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
        count_new = next(iter(new.values())).shape[0]
        if th.random_t_center and count_new:
            new["t_center"] = torch.rand(count_new, 1).to(dev)
        append_gaussians(params, optimizer, new)
        self._fit(params.count)  # the new Gaussians have no statistics yet
        prune = self._prune_mask(params, step, big=True)
        prune[:n] |= split  # split parents go
        self._keep(params, optimizer, (~prune).to(dev))
        self._reset_stats(params.count)
        self.log.append({"step": step, "cloned": int(clone.sum()), "split": int(split.sum()),
                         "pruned": int(prune.sum()) - int(split.sum()), "count": params.count})

    def reset_opacity(self, params: STGParams, optimizer) -> None:
        """opacity = min(opacity, reset_opacity) (in logit space), Adam moments of opacity zeroed."""
        cap = math.log(self.thresholds.reset_opacity / (1 - self.thresholds.reset_opacity))
        set_values(params, optimizer, "opacity_logit", params["opacity_logit"].detach().clamp(max=cap))

    # -- checkpoints -----------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {"grad_sum": self.grad_sum.clone(), "grad_count": self.grad_count.clone(),
                "max_radius": self.max_radius.clone(), "rounds_done": self.rounds_done, "log": list(self.log),
                "schedule": asdict(self.schedule), "thresholds": asdict(self.thresholds), "extent": self.extent}

    def load_state_dict(self, state: dict) -> None:
        self.grad_sum, self.grad_count = state["grad_sum"].clone(), state["grad_count"].clone()
        self.max_radius = state["max_radius"].clone()
        self.rounds_done, self.log = int(state["rounds_done"]), list(state["log"])
