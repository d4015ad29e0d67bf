"""Guided sampling of Gaussians (the paper's Sec. 4.4) as a strategy (stg_train.strategy.base).

Distant or textureless regions that the initial points miss stay blurry: density control only grows
Gaussians near existing ones. Guided sampling adds Gaussians along the rays of pixels with large errors,
within the coarse depth range, after the loss has settled. It follows the reference implementation:

1. At `schedule.guided_start` (1600 of 30k iterations, scaled like the rest of the schedule) every
   training view is rendered at the step's time and compared with its ground truth (3DGS's SSIM; the
   picture as the canonical scene would look where the cameras are modelled, StepContext); the
   (up to) `views` = 2 views with the lowest SSIM below `select_ssim` = 0.91 are chosen (the reference
   chooses none unless at least two are below: `min_views`).
2. At guided_start and then every `schedule.guided_every` steps, one chosen view is rendered again at
   that step's time; if its SSIM is below `act_ssim` = 0.88 (a structure that is already good needs
   nothing) Gaussians are added:
   - error = sum over rgb of |image / (mean(image) + 0.01) - gt / (mean(gt) + 0.01)|; error pixels are
     those above the `error_quantile` = 0.6 quantile;
   - 16x16 patches (`patch`) with more than `patch_fraction` = 85% error pixels are selected; pixels
     within `border` = 10% of the image edges are left out;
   - every error pixel of a selected patch gets `samples` = 2 Gaussians on its ray at camera depths
     linspace(0.7 d, 7.5 d) (`ratio_start`, `ratio_end`), each times (1 + 0.1 (U - 0.5)) (5% jitter),
     where d is the patch's coarse depth: the median of the rendered expected depth over the patch's
     pixels with alpha >= `min_alpha`; patches without any fall back to the camera's far bound
     (dataset.bounds), else the largest rendered depth of the view. The reference uses one d per
     view, its largest rendered depth (`depth="max"`); the patch median was measured against it
     (docs/training.md, "Deviations from the reference"). Unlike the reference, the far end
     is clipped to the camera's far bound when the dataset has one (7.5 d may lie far behind the
     scene's last surface);
   - colour: the ground truth at the pixel; spatial opacity 0.1; a uniform random temporal centre;
     scale from the 3 nearest points; no motion or rotation (STGParams.new_rows).
   DensityControl prunes the ones that stay useless.

Random numbers (depth jitter, temporal centres) come from torch's global CPU generator, which the
trainer checkpoints, so a resumed run adds the same Gaussians.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import torch
from torch import Tensor

from ..losses import ssim
from ..params import STGParams
from .base import StepContext, Strategy
from .ops import append_gaussians
from .schedule import Schedule


#: GuidedSettings.depth values.
GUIDED_DEPTHS = ("median", "max")


@dataclass(frozen=True)
class GuidedSettings:
    """Thresholds of guided sampling (the reference implementation's values); see the module docstring."""

    views: int = 2
    select_ssim: float = 0.91
    act_ssim: float = 0.88
    error_quantile: float = 0.6
    patch: int = 16
    patch_fraction: float = 0.85
    border: float = 0.1
    ratio_start: float = 0.7
    ratio_end: float = 7.5
    samples: int = 2
    jitter: float = 0.1
    opacity: float = 0.1
    min_alpha: float = 0.5
    # d, the depth that the samples' range multiplies: "median" (ours: the patch's median rendered
    # depth) or "max" (the reference's depthmax: the view's largest rendered depth, one value per view)
    depth: str = "median"
    # act only when at least this many training views are below select_ssim (the reference: 2)
    min_views: int = 1

    def __post_init__(self):
        if self.depth not in GUIDED_DEPTHS:
            raise ValueError(f"depth must be one of {GUIDED_DEPTHS}, got {self.depth!r}")


def _patch_view(x: Tensor, p: int) -> Tensor:
    """(H, W) -> (H' / p, W' / p, p * p) patches of x zero-padded to multiples of p."""
    h, w = x.shape
    hp, wp = -(-h // p) * p, -(-w // p) * p
    x = torch.nn.functional.pad(x[None, None].float(), (0, wp - w, 0, hp - h))[0, 0]
    return x.reshape(hp // p, p, wp // p, p).permute(0, 2, 1, 3).reshape(hp // p, wp // p, p * p)


def _unpatch(x: Tensor, p: int, h: int, w: int) -> Tensor:
    """(H' / p, W' / p) per-patch values -> (H, W) per-pixel values."""
    return x.repeat_interleave(p, 0).repeat_interleave(p, 1)[:h, :w]


def error_pixels(image: Tensor, gt: Tensor, settings: GuidedSettings = GuidedSettings()) -> Tensor:
    """(H, W) bool: error pixels of selected patches, borders excluded. image, gt (H, W, 3) in [0, 1] (gt a
    little above 1 where a camera's falloff or appearance was divided out, StepContext.ground_truth)."""
    s = settings
    diff = (image / (image.mean() + 0.01) - gt / (gt.mean() + 0.01)).abs().sum(-1)
    flat = torch.sort(diff.reshape(-1)).values
    error = diff > flat[int(flat.numel() * s.error_quantile)]
    h, w = error.shape
    patches = _patch_view(error, s.patch).sum(-1) > s.patch * s.patch * s.patch_fraction
    mask = _unpatch(patches, s.patch, h, w) & error
    bh, bw = int(h * s.border), int(w * s.border)
    inner = torch.zeros_like(mask)
    inner[bh:h - bh, bw:w - bw] = True
    return mask & inner


def coarse_depth(depth: Tensor, alpha: Tensor, fallback: float, settings: GuidedSettings = GuidedSettings()) -> Tensor:
    """(H, W) per-patch median of the rendered expected depth over pixels with alpha >= min_alpha;
    `fallback` for patches without such pixels."""
    p, (h, w) = settings.patch, depth.shape
    seen = _patch_view(alpha >= settings.min_alpha, p) > 0.5  # padding is unseen
    med = torch.nanmedian(torch.where(seen, _patch_view(depth, p), torch.nan), dim=-1).values
    med = torch.where(torch.isnan(med), torch.full_like(med, fallback), med)
    return _unpatch(med, p, h, w)


def ray_samples(camera, rows: Tensor, cols: Tensor, depth: Tensor, far: float | None,
                 settings: GuidedSettings = GuidedSettings()) -> tuple[np.ndarray, Tensor]:
    """Points (K * samples, 3) float64 along the rays of pixels (rows, cols) (K,) of `camera` at camera
    depths linspace(ratio_start d, ratio_end d) (far end clipped to `far`), 5% jitter; depth (K,) = d.
    Returns the points and their camera depths (K * samples,). Sample-major order: all pixels' first
    samples, then the second ones. Through a fisheye, the points of rays at or beyond 90 degrees off
    its axis are non-finite (Camera.unproject)."""
    s = settings
    d = depth.double().cpu()
    lo, hi = s.ratio_start * d, s.ratio_end * d
    if far is not None:
        hi = torch.maximum(torch.clamp(hi, max=far), lo)
    frac = torch.linspace(0, 1, s.samples, dtype=torch.float64) if s.samples > 1 else torch.zeros(1).double()
    z = lo[None] + (hi - lo)[None] * frac[:, None]  # (samples, K)
    z = z * (1 + s.jitter * (torch.rand(z.shape, dtype=torch.float64) - 0.5))
    u = np.tile(cols.cpu().numpy() + 0.5, s.samples)
    v = np.tile(rows.cpu().numpy() + 0.5, s.samples)
    return camera.unproject(u, v, z.reshape(-1).numpy()), z.reshape(-1)


class GuidedSampling(Strategy):
    """The guided-sampling strategy (see the module docstring); place it after DensityControl.

    schedule: its guided_start / guided_every fields; settings: GuidedSettings. `scores`: [ssim, camera
    index] of every training view at guided_start, lowest first; `log`: one entry per sampling attempt:
    step, camera index, ssim, added (Gaussians).
    """

    def __init__(self, schedule: Schedule, settings: GuidedSettings = GuidedSettings()):
        self.schedule, self.settings = schedule, settings
        self.chosen: list[int] | None = None  # camera indices chosen at guided_start
        self.done = 0  # sampling attempts made
        self.scores: list[list] = []
        self.log: list[dict] = []

    def step_post_backward(self, params: STGParams, optimizer: torch.optim.Optimizer, step: int,
                           context: StepContext) -> None:
        """From schedule.guided_start: choose the views once, then sample one view every guided_every."""
        s = self.schedule
        if step < s.guided_start:
            return
        if self.chosen is None:
            self.chosen = self.choose_views(context)
        if self.done < len(self.chosen) and step >= s.guided_start + self.done * s.guided_every:
            added, score = self.sample_view(params, optimizer, context, self.chosen[self.done])
            self.log.append({"step": step, "camera": self.chosen[self.done], "ssim": score, "added": added})
            self.done += 1

    @torch.no_grad()
    def choose_views(self, context: StepContext) -> list[int]:
        """Training cameras (up to settings.views) with the lowest SSIM below select_ssim at the step's time."""
        scores = []
        for ci in context.dataset.train_cameras:
            rgb, _ = context.render(ci, context.tau)
            scores.append((ssim(rgb.clamp(0, 1)[None], context.ground_truth(ci, context.frame)[None]).item(), ci))
        scores.sort()
        self.scores = [[score, ci] for score, ci in scores]
        below = [ci for score, ci in scores if score < self.settings.select_ssim]
        return below[:self.settings.views] if len(below) >= self.settings.min_views else []

    @torch.no_grad()
    def sample_view(self, params: STGParams, optimizer, context: StepContext, camera_index: int) -> tuple[int, float]:
        """Render camera_index at the step's time; add Gaussians if its SSIM is below act_ssim.
        Returns (Gaussians added, SSIM)."""
        rgb, out = context.render(camera_index, context.tau)
        rgb = rgb.clamp(0, 1)
        gt = context.ground_truth(camera_index, context.frame)
        score = ssim(rgb[None], gt[None]).item()
        if score >= self.settings.act_ssim:
            return 0, score
        ds = context.dataset
        camera = ds.cameras[camera_index]
        far = None if ds.bounds is None else float(ds.bounds[camera_index][1])
        new = self.new_gaussians(params, camera, rgb, gt, out.depth, out.alpha, far)
        if new is None:
            return 0, score
        append_gaussians(params, optimizer, new)
        return int(new["xyz"].shape[0]), score

    def new_gaussians(self, params: STGParams, camera, image: Tensor, gt: Tensor, depth: Tensor, alpha: Tensor,
                      far: float | None) -> dict[str, Tensor] | None:
        """Raw rows of the Gaussians guided sampling adds for one view (None if no pixel qualifies).
        image, gt (H, W, 3) in [0, 1] (gt as error_pixels'); depth, alpha (H, W) from the render; far: the
        camera's far bound. The new Gaussians' colours are gt's."""
        s = self.settings
        mask = error_pixels(image, gt, s)
        rows, cols = torch.nonzero(mask, as_tuple=True)
        if rows.numel() == 0:
            return None
        seen = alpha >= s.min_alpha
        if far is not None:
            fallback = far
        elif bool(seen.any()):
            fallback = float(depth[seen].max())
        else:
            fallback = 1.0
        if s.depth == "max":
            view_max = float(depth[seen].max()) if bool(seen.any()) else fallback
            d = torch.full(rows.shape, view_max, dtype=depth.dtype)
        else:
            d = coarse_depth(depth.detach(), alpha.detach(), fallback, s)[rows, cols]
        xyz, _ = ray_samples(camera, rows, cols, d, far, s)
        colour = gt[rows, cols].repeat(s.samples, 1)
        t_center = torch.rand(xyz.shape[0])
        # A fisheye's rays at or beyond 90 degrees off its axis have no point at a positive depth.
        keep = torch.as_tensor(np.isfinite(xyz).all(1))
        if not bool(keep.any()):
            return None
        return params.new_rows(torch.as_tensor(xyz)[keep], colour[keep], t_center[keep], opacity=s.opacity)

    # -- checkpoints -----------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {"chosen": self.chosen, "done": self.done, "scores": list(self.scores), "log": list(self.log),
                "settings": asdict(self.settings)}

    def load_state_dict(self, state: dict) -> None:
        self.chosen = None if state["chosen"] is None else [int(c) for c in state["chosen"]]
        self.done, self.log = int(state["done"]), list(state["log"])
        self.scores = list(state.get("scores", []))
