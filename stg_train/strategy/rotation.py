"""The reference implementation's separation of rotating from moving Gaussians, as a strategy.

At iteration 8001 of its 30k (N3V settings; `Schedule.separate_at`, stretched like the rest of the
schedule) the reference keeps the rotation velocity omega only for Gaussians that move, are mid-sized
and opaque (`zero_omegabymotion`): sum |motion[0:3]| > `min_speed`, max scale in (`min_scale`,
`max_scale`), opacity > `min_opacity` (absolute values, in its scenes' world units). Every other omega
is set to 0. From then on, a Gaussian with omega = 0 keeps it (its omega gradient is dropped), and a
Gaussian that kept its omega keeps its rotation at the temporal centre (its rotation gradient is
dropped): the moving ones rotate with time, the others hold a fixed orientation.

The reference keeps a boolean mask and zeroes gradients through it; here the kept Gaussians are
recognised by a non-zero omega, so the rule needs no state that other strategies' edits (appends,
pruning) could misalign, and Adam's moments of the edited rows are zeroed so that nothing drifts.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from ..params import STGParams
from .base import StepContext, Strategy
from .ops import set_values
from .schedule import Schedule


@dataclass(frozen=True)
class SeparationThresholds:
    """zero_omegabymotion's thresholds (absolute, world units and normalised time)."""

    min_speed: float = 0.3  # sum of |linear motion coefficients|, world units per unit of normalised time
    min_scale: float = 0.2
    max_scale: float = 0.6
    min_opacity: float = 0.7


class SeparateRotation(Strategy):
    """Keep omega only for moving, mid-sized, opaque Gaussians at `schedule.separate_at`; afterwards
    freeze omega where it is 0 and the rotation where it is not (see the module docstring).
    `kept`: how many Gaussians kept their omega (None before the separation)."""

    def __init__(self, schedule: Schedule, thresholds: SeparationThresholds = SeparationThresholds()):
        self.schedule, self.thresholds = schedule, thresholds
        self.kept: int | None = None

    def keep_mask(self, params: STGParams) -> torch.Tensor:
        """(N,) bool on the parameters' device: the Gaussians that keep their omega."""
        th = self.thresholds
        with torch.no_grad():
            speed = params["motion"][:, 0:3].abs().sum(1)
            size = torch.exp(params["log_scale"]).amax(1)
            opacity = torch.sigmoid(params["opacity_logit"]).reshape(-1)
        return (speed > th.min_speed) & (size > th.min_scale) & (size < th.max_scale) & (opacity > th.min_opacity)

    def step_post_backward(self, params: STGParams, optimizer, step: int, context: StepContext) -> None:
        at = self.schedule.separate_at
        if not at or step < at or not params.trainable("rotation"):
            return
        if step == at:
            keep = self.keep_mask(params)
            set_values(params, optimizer, "omega", params["omega"].detach() * keep[:, None])
            self.kept = int(keep.sum())
        moving = params["omega"].detach().abs().sum(1) > 0
        for name, rows in (("omega", ~moving), ("rotation", moving)):
            grad = params.raw[name].grad
            if grad is not None:
                grad[rows] = 0
        if step == at:  # the kept Gaussians' rotation moments too, so that Adam does not move it on
            state = optimizer.state.get(params.raw["rotation"], {})
            for key in ("exp_avg", "exp_avg_sq"):
                if key in state:
                    state[key][moving] = 0

    def state_dict(self) -> dict:
        return {"kept": self.kept}

    def load_state_dict(self, state: dict) -> None:
        self.kept = state.get("kept")
