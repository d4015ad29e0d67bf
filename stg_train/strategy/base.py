"""The strategy protocol: plug-ins that edit the Gaussians around backward(), in gsplat's shape.

Each training step the trainer calls, for every strategy in its list (DensityControl first):

    strategy.step_pre_backward(params, optimizer, step, context)    after the renders, before backward()
    strategy.step_post_backward(params, optimizer, step, context)   after backward(), before optimizer.step()

`context` (StepContext) carries the step's renders and what a strategy may need beyond them (the
dataset, the step's frame and time, functions that render a training view and fetch its ground truth).
A strategy edits the Gaussians only through stg_train.strategy.ops, which keeps every parameter's Adam
state in step; it may append Gaussians (new rows go at the end, and DensityControl extends its
statistics for them) but leaves removing them to DensityControl. Random numbers come from torch's
global generator, which the trainer checkpoints with state_dict(), so a resumed run reaches the same
state.
"""
from __future__ import annotations

from typing import Callable, NamedTuple


class StepContext(NamedTuple):
    """What a strategy sees of one training step.

    dataset: the stg_train.data.Dataset; frame: the step's frame index; tau: its normalised time;
    renders: [(camera, stg_train.render.RenderOutput)] of the step's batch (their means2d carry the
    screen-space gradients after backward); render(camera_index, tau) -> (rgb (H, W, 3), RenderOutput)
    of the current parameters (call it under torch.no_grad()); ground_truth(camera_index, frame) ->
    (H, W, 3) float on the device: the camera's picture as the canonical scene would look (what render
    gives at a perfect fit: the camera's lens falloff and appearance undone, CameraRig.canonical;
    the picture itself, in [0, 1], where the cameras are not modelled).
    """

    dataset: object
    frame: int
    tau: float
    renders: list
    render: Callable
    ground_truth: Callable


class Strategy:
    """A plug-in around backward() (see the module docstring). Subclasses override what they use."""

    def step_pre_backward(self, params, optimizer, step: int, context: StepContext) -> None:
        """Called after the step's renders, before loss.backward() (step counts from 1)."""

    def step_post_backward(self, params, optimizer, step: int, context: StepContext) -> None:
        """Called after loss.backward(), before optimizer.step() (step counts from 1)."""

    def state_dict(self) -> dict:
        """What a checkpoint keeps of the strategy."""
        return {}

    def load_state_dict(self, state: dict) -> None:
        """Restore state_dict()'s result."""
