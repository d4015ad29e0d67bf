"""Where training starts: the initial points, from structure-from-motion (stg_train.data.sfm) or the
view volume (stg_train.data.volume), and which of the two a dataset gets by default."""
from __future__ import annotations

import warnings
from typing import Callable

import numpy as np

from .dataset import DataError
from .sfm import MIN_SFM_POINTS, sfm_points
from .volume import sample_view_volume

METHODS = ("sfm", "volume")


def default_method(dataset) -> str:
    """"volume" when the dataset has near/far depth bounds (N3V, the demo), else "sfm" (docs/training.md
    compares the two)."""
    return "volume" if dataset.bounds is not None else "sfm"


def initial_points(dataset, method: str, num_points: int, rng: np.random.Generator, every: int = 1,
                   depth_candidates: int = 0, min_points: int = MIN_SFM_POINTS, cache_dir=None,
                   progress: Callable[[int, int], None] | None = None):
    """Initial Gaussians' xyz (N, 3), rgb (N, 3) in [0, 1] and t_center (N,) for the trainer.

    method "sfm": sfm_points of every `every`-th frame, at most num_points of them (a random subset
    when SfM finds more); fewer than min_points SfM points warn (UserWarning naming the dataset) and
    fall back to "volume". method "volume": num_points from stg_train.data.volume.sample_view_volume
    (depth_candidates: its photo-consistency depth search), which needs dataset.bounds (near/far per
    camera): DataError naming the dataset when they are missing.
    """
    if method not in METHODS:
        raise ValueError(f"init must be 'sfm' or 'volume', got {method!r}")
    where = dataset.path or dataset
    if method == "sfm":
        xyz, rgb, t_center = sfm_points(dataset, every=every, cache_dir=cache_dir, progress=progress)
        if len(xyz) >= min_points:
            if len(xyz) > num_points:
                idx = np.sort(rng.choice(len(xyz), num_points, replace=False))
                xyz, rgb, t_center = xyz[idx], rgb[idx], t_center[idx]
            return xyz.astype(np.float64), rgb, t_center
        if dataset.bounds is None:
            raise DataError(f"{where}: structure-from-motion found only {len(xyz)} points (fewer than "
                            f"{min_points}), and the layout has no near/far depth bounds for the view-volume "
                            "sampler; check that the images are textured and overlap and that the poses are right")
        warnings.warn(f"{where}: structure-from-motion found only {len(xyz)} points (fewer than {min_points}); "
                      "initialising from the view volume instead", stacklevel=2)
    elif dataset.bounds is None:
        raise DataError(f"{where}: the view-volume initialisation needs near/far depth bounds, which this layout "
                        "does not provide; use the SfM initialisation (--init sfm)")
    return sample_view_volume(dataset, num_points, rng, depth_candidates=depth_candidates)
