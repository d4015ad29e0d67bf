"""Where training starts: the initial points, and which initialisation a dataset gets by default.

    sfm       structure-from-motion points (stg_train.data.sfm) only;
    volume    samples in the training cameras' view volume at photo-consistent depths
              (stg_train.data.volume), between the cameras' near/far depth bounds;
    combined  the SfM points (at most --points x the fraction of the training cameras' pixels they
              cover, stg_train.data.coverage), and the rest of --points as view-volume samples drawn
              from the pixels that the projected SfM points leave uncovered;
    auto      default_method: volume, with the bounds from wherever they come (below); SfM runs only
              when the dataset has none.

Layouts without stored bounds get them from the COLMAP model's points, from --near/--far, or else from
the SfM points (stg_train.data.bounds). docs/training.md compares the initialisations.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..choices import INIT_METHODS
from .bounds import MIN_VISIBLE, bounds_from_points, describe
from .coverage import coverage_masks, coverage_radius
from .dataset import DataError
from .sfm import MIN_SFM_POINTS, sfm_points
from .volume import sample_view_volume

METHODS = INIT_METHODS


@dataclass
class InitialPoints:
    """The initial points and how they were made.

    xyz (N, 3) float64 world units, rgb (N, 3) float32 in [0, 1], t_center (N,) float32 normalised time;
    method: the initialisation carried out ("sfm", "volume" or "combined"; "volume" also when SfM found
    too few points); sfm_points, volume_points: how many of the N come from each; coverage: per training
    camera, the fraction of its pixels covered by the kept SfM points (None unless combined); radius: the
    coverage radius in pixels; bounds (C, 2) and bounds_source: the near/far depth bounds known after
    the initialisation (Dataset.bounds_source values; None when there are none).
    """

    xyz: np.ndarray
    rgb: np.ndarray
    t_center: np.ndarray
    method: str
    sfm_points: int = 0
    volume_points: int = 0
    coverage: np.ndarray | None = None
    radius: int = 0
    bounds: np.ndarray | None = None
    bounds_source: str | None = None

    def summary(self) -> dict:
        """JSON-able figures: method, point counts, coverage (mean, min, max), bounds source."""
        out = {"method": self.method, "sfm_points": self.sfm_points, "volume_points": self.volume_points,
               "bounds_source": self.bounds_source}
        if self.coverage is not None:
            out.update(coverage=float(np.mean(self.coverage)), coverage_min=float(np.min(self.coverage)),
                       coverage_max=float(np.max(self.coverage)), coverage_radius_px=self.radius)
        return out

    def describe(self) -> str:
        """Lines for the user: the split, the coverage and the bounds."""
        if self.method == "combined":
            cov = self.coverage
            lines = [f"initial points: {self.sfm_points} SfM + {self.volume_points} view-volume samples in the holes "
                     f"(combined); the SfM points cover {np.mean(cov):.0%} of the training cameras' pixels "
                     f"({np.min(cov):.0%}-{np.max(cov):.0%} per camera, within {self.radius} px)"]
        elif self.method == "sfm":
            lines = [f"initial points: {self.sfm_points} SfM points"]
        else:
            lines = [f"initial points: {self.volume_points} view-volume samples"]
        if self.bounds is not None:
            lines.append(describe(self.bounds, self.bounds_source))
        return "\n".join(lines)


def default_method(dataset) -> str:
    """--init auto: "volume" for every dataset; a layout without near/far bounds gets them from the SfM
    points (docs/notes/initial-points.md compares the initialisations on one scene in two layouts)."""
    return "volume"


def resolve_method(dataset, method: str | None) -> str:
    """`method`, with "auto" (or None) replaced by default_method(dataset); ValueError for unknown ones."""
    if method is None or method == "auto":
        return default_method(dataset)
    if method not in METHODS:
        raise ValueError(f"init must be one of {', '.join(METHODS)}, got {method!r}")
    return method


def _subset(rng, count: int, *arrays):
    """A sorted random subset of `count` rows of each array (all of them when they are fewer)."""
    if len(arrays[0]) <= count:
        return arrays
    idx = np.sort(rng.choice(len(arrays[0]), count, replace=False))
    return tuple(a[idx] for a in arrays)


def initial_points(dataset, method: str | None, num_points: int, rng: np.random.Generator, every: int = 1,
                   depth_candidates: int = 0, min_points: int = MIN_SFM_POINTS, cache_dir=None,
                   progress: Callable[[int, int], None] | None = None) -> InitialPoints:
    """The initial points of `method` (METHODS; see the module doc) for the trainer.

    num_points: the initial Gaussians (the most SfM points kept: a random subset beyond); every: SfM on
    every `every`-th frame (sfm_points); depth_candidates: the view-volume sampler's photo-consistency
    depth search; cache_dir, progress: sfm_points'. SfM runs for "sfm" and "combined", and for "volume"
    when the dataset has no near/far bounds (they then come from the SfM points). When SfM finds fewer
    than min_points points, "sfm" and "combined" warn (UserWarning naming the dataset) and fall back to
    "volume"; without bounds from elsewhere that is a DataError naming the dataset.
    """
    method = resolve_method(dataset, method)
    where = dataset.path or dataset
    bounds, source = dataset.bounds, dataset.bounds_source
    if method == "volume" and bounds is not None:
        return _volume(dataset, num_points, rng, depth_candidates, bounds, source)
    xyz, rgb, t_center = sfm_points(dataset, every=every, cache_dir=cache_dir, progress=progress)
    xyz = xyz.astype(np.float64)
    enough = len(xyz) >= min_points
    if bounds is None and enough:
        bounds, source = bounds_from_points(dataset.cameras, xyz), "sfm"
        source = None if bounds is None else source
    if method == "sfm" and enough:
        xyz, rgb, t_center = _subset(rng, num_points, xyz, rgb, t_center)
        return InitialPoints(xyz, rgb, t_center, "sfm", sfm_points=len(xyz), bounds=bounds, bounds_source=source)
    if bounds is None:
        found = (f"structure-from-motion found only {len(xyz)} points" if not enough else
                 f"fewer than {MIN_VISIBLE} of the {len(xyz)} SfM points lie in any camera's view")
        if method == "volume":
            raise DataError(f"{where}: the view-volume initialisation needs near/far depth bounds: the layout has "
                            f"none, and {found} to derive them from; give them with --near and --far")
        raise DataError(f"{where}: {found} (the initialisation needs {min_points}), and there are no near/far "
                        "depth bounds for the view-volume sampler; give them with --near and --far, or check "
                        "that the images are textured and overlap and that the poses are right")
    if method in ("sfm", "combined") and not enough:
        warnings.warn(f"{where}: structure-from-motion found only {len(xyz)} points (fewer than {min_points}); "
                      "initialising from the view volume instead", stacklevel=2)
    if method == "combined" and enough:
        return _combined(dataset, num_points, rng, depth_candidates, xyz, rgb, t_center, bounds, source)
    return _volume(dataset, num_points, rng, depth_candidates, bounds, source)


def _with_bounds(dataset, bounds, source):
    return dataset if dataset.bounds is not None else dataset.with_bounds(bounds, source)


def _volume(dataset, num_points, rng, depth_candidates, bounds, source) -> InitialPoints:
    xyz, rgb, t_center = sample_view_volume(_with_bounds(dataset, bounds, source), num_points, rng,
                                            depth_candidates=depth_candidates)
    return InitialPoints(xyz, rgb, t_center, "volume", volume_points=len(xyz), bounds=bounds, bounds_source=source)


def _combined(dataset, num_points, rng, depth_candidates, xyz, rgb, t_center, bounds, source) -> InitialPoints:
    """SfM points plus view-volume samples in the pixels they leave uncovered (the module doc)."""
    cams = [dataset.cameras[i] for i in dataset.train_cameras]
    radius = coverage_radius(dataset.width)
    covered = coverage_masks(cams, xyz, radius)
    most = int(round(num_points * covered.mean()))  # the covered share of the points
    if len(xyz) > most:  # a subset, which leaves more holes
        xyz, rgb, t_center = _subset(rng, most, xyz, rgb, t_center)
        covered = coverage_masks(cams, xyz, radius)
    n_volume = num_points - len(xyz) if not covered.all() else 0
    coverage = covered.reshape(len(cams), -1).mean(axis=1)
    parts = [(xyz, rgb.astype(np.float32), t_center.astype(np.float32))]
    if n_volume > 0:
        parts.append(sample_view_volume(_with_bounds(dataset, bounds, source), n_volume, rng,
                                        depth_candidates=depth_candidates, mask=~covered))
    xyz_all, rgb_all, t_all = (np.concatenate(a) for a in zip(*parts))
    return InitialPoints(xyz_all.astype(np.float64), rgb_all, t_all, "combined", sfm_points=len(xyz),
                         volume_points=max(n_volume, 0), coverage=coverage, radius=radius, bounds=bounds,
                         bounds_source=source)
