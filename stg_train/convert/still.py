"""Still Gaussians: those whose centre hardly moves while they are drawn (issue 50; numpy only).

    travel(segment) -> (N,)              how far each centre gets from its position at the temporal centre
    still_mask(segment, distance) -> (N,) bool   travel below `distance`

A trained model gives almost every Gaussian some motion, also on the static parts of a scene.
Fine-tuning (finetune.py, `still`) sets the motion and rotation velocity of the still Gaussians to 0
and keeps them there while the others make up for it; the web preset's coder then stores their rows
as one repeated symbol, almost for free (docs/convert.md, "Still Gaussians").
"""
from __future__ import annotations

import numpy as np

from stg_runtime.model import Segment
from stg_runtime.spec import MIN_ALPHA, evaluate_oracle


def travel(segment: Segment) -> np.ndarray:
    """(N,) float64 world units: the largest distance between a Gaussian's centre at a frame time
    tau = j / num_frames (j = 0 .. num_frames - 1) where it is drawn (opacity(tau) >= MIN_ALPHA) and its
    centre at its temporal centre (position[:, 0]): what setting its motion to 0 moves it by. 0 for a
    Gaussian drawn at no frame."""
    centre = segment.position[:, 0].astype(np.float64)
    out = np.zeros(segment.count)
    for j in range(segment.num_frames):
        at = evaluate_oracle(segment, j / segment.num_frames)
        offset = np.linalg.norm(at["means"] - centre, axis=1)
        out = np.where(at["opacities"] >= MIN_ALPHA, np.maximum(out, offset), out)
    return out


def still_mask(segment: Segment, distance: float) -> np.ndarray:
    """(N,) bool: the Gaussians whose travel (world units) is below `distance`."""
    return travel(segment) < float(distance)
