"""The rig measured again during training, through the model's own geometry.

A run whose rig was measured before training ("auto" settings, stg_train.rig.self_calibration) renders
its depth through the training cameras as it holds them at REMEASURE_AT of its steps, and from the
pixels that geometry pairs between neighbouring cameras (measure_rig_with_depth) takes again the lens
falloff (the flow's matches leave the corners about 0.02 too bright) where one was measured, and where
an appearance is learned, the cameras' colour gains, which then hold its transforms
(docs/training.md, "Real captures"). What it finds is checked against what the run already has
(FALLOFF_AGREEMENT, GAIN_AGREEMENT): a model whose geometry is not yet the scene's is not trusted.
"""
from __future__ import annotations

from typing import Callable

import numpy as np
import torch

from .lens import known_falloff
from .self_calibration import LENS_SPREAD, UNCERTAIN, measure_rig_with_depth, measured_frames

#: The fraction of a run's steps at which the rig is measured again.
REMEASURE_AT = 1 / 3
#: The falloff so measured is trained on with unless its corner brightness differs from the flow's by
#: more than this (a model whose geometry is not yet the scene's: a very short run).
FALLOFF_AGREEMENT = 0.05
#: ... and the colour gains held unless they differ from what the appearance has learned by more than
#: this (RMS of the logs over cameras and channels; about 0.012 at that point on the realistic captures).
GAIN_AGREEMENT = 0.05


def remeasure_plan(falloff_auto: bool, config, calibration) -> dict:
    """What a run measures again through its model's geometry, from what the rig's measurement before
    training decided (calibrate_rig's config and RigCalibration; falloff_auto: the falloff was "auto"):
    "falloff" where it was measured and trained with; "gains" where an appearance is learned and the
    lenses were measured to share one falloff (the geometric fit assumes they do)."""
    estimate = calibration.estimate
    lenses_alike = estimate is not None and estimate.lens_spread <= LENS_SPREAD
    return {"falloff": bool(falloff_auto and config.lens_falloff is not None),
            "gains": bool(config.appearance is True and lenses_alike)}


def remeasure_due(plan: dict, step: int, steps: int) -> bool:
    """Whether step `step` (1-based) of a run of `steps` is the one the rig is measured again after."""
    return any(plan.values()) and step == max(1, round(steps * REMEASURE_AT))


@torch.no_grad()
def remeasure_rig(rig, render: Callable, frames=None) -> None:
    """Measure `rig` (a CameraRig) again through the model's geometry: its depth rendered (render(camera,
    frame) -> (rgb, RenderOutput), at a frame index of the dataset) through the training cameras as it
    holds them, at `frames` (default the first and the middle frame, as before training), as rig.remeasure
    says: train on with that lens falloff unless it cannot be measured or trusted, and set each camera's
    appearance to its measured colour gains and hold it (CameraRig.hold_appearance) unless they stray
    from what it has learned. rig.remeasure_note says what was done."""
    ds = rig.dataset
    frames = measured_frames(ds) if frames is None else tuple(frames)
    cameras = rig.refined(ds.cameras)
    depths = {}
    for c in ds.train_cameras:
        for f in frames:
            out = render(cameras[c], f)[1]
            depths[c, f] = (out.depth.cpu().numpy(), out.alpha.cpu().numpy())
    said = f"the rig measured again at step {rig.step}, from the model's geometry"
    try:
        found = measure_rig_with_depth(ds, cameras, depths, frames)
    except ValueError as e:
        rig.remeasure_note = f"{said}: {e}; training on as before"
        return
    notes = []
    try:
        if rig.remeasure.get("falloff"):
            notes.append(_take_falloff(rig, found))
    except ValueError as e:  # a geometry that gets the falloff wrong is not trusted with the colours
        notes.append(f"{e}: not taken")
    else:
        if rig.remeasure.get("gains") and rig.appearance is not None:
            try:
                notes.append(_take_gains(rig, found))
            except ValueError as e:
                notes.append(f"{e}: not taken")
    rig.remeasure_note = f"{said}: " + "; ".join(notes)


def _take_falloff(rig, found) -> str:
    """Train on with the falloff of `found` (a GeometricMeasurement); ValueError when it is uncertain,
    out of range or strays from the flow's (FALLOFF_AGREEMENT)."""
    flow_corner = 1 + sum(rig.lens_falloff)  # the corner brightness measured before training
    if found.corner_error > UNCERTAIN:
        raise ValueError(f"its falloff is uncertain (+-{found.corner_error:.3f})")
    if abs(found.corner_brightness - flow_corner) > FALLOFF_AGREEMENT:
        raise ValueError(f"its corner brightness {found.corner_brightness:.3f} disagrees with the flow's "
                         f"{flow_corner:.3f}")
    k = known_falloff(found.k)
    rig.take_falloff(k)
    return (f"lens falloff K1 {k[0]:.3f}, K2 {k[1]:.3f} (corner brightness {found.corner_brightness:.3f}; was "
            f"{flow_corner:.3f} from the flow)")


def _take_gains(rig, found) -> str:
    """Hold the appearance at the colour gains of `found`, unless they stray from the diagonals it has
    learned by more than GAIN_AGREEMENT (RMS of the logs, each channel's mean over the cameras
    removed): a model whose geometry is not yet the scene's."""
    learned = np.array([np.diag(a["matrix"]) for a in rig.appearance.summary()])
    if np.any(learned <= 0):
        raise ValueError("the appearance learned so far has a colour gain at or below 0")
    stray = np.log(found.gains) - np.log(learned)
    stray = float(np.sqrt(np.mean((stray - stray.mean(0)) ** 2)))
    if stray > GAIN_AGREEMENT:
        raise ValueError(f"its colour gains differ from the ones learned by {100 * stray:.1f} % (RMS)")
    rig.hold_appearance(found.gains)
    return f"the cameras' colours set from it and held (they differed from the ones learned by {100 * stray:.1f} %)"
