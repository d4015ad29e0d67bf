"""Near and far depth bounds per camera, for every layout: what the view-volume initialisation
(stg_train.data.volume) samples between and what guided sampling clips its far end to.

Where they come from (Dataset.bounds_source):
    "layout"  the layout stores them (N3V's poses_bounds.npy);
    "colmap"  the 3D points of the layout's COLMAP model (rig, reference), via bounds_from_points;
    "user"    stg-train --near/--far (load_dataset(depth_range=...)), the same for every camera;
    "sfm"     the initialisation's structure-from-motion points, via bounds_from_points.

bounds_from_points takes, per camera, the depths of the points in front of it that project into its
image, and widens robust percentiles of them by a margin: near = LOW_PERCENTILE-th percentile / MARGIN,
far = HIGH_PERCENTILE-th percentile x MARGIN. A camera that sees fewer than MIN_VISIBLE points gets the
median bounds of the others.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from stg_runtime.camera import Camera

from .visibility import sees

#: Dataset.bounds_source values, and how stg-train describes them.
SOURCES = {"layout": "the layout's near/far bounds", "colmap": "the COLMAP model's points",
           "user": "--near/--far", "sfm": "the SfM points"}
LOW_PERCENTILE, HIGH_PERCENTILE = 1.0, 99.0
#: Factor by which the percentiles are widened (near divided by it, far multiplied).
MARGIN = 1.25
#: Fewest points a camera must see for bounds of its own.
MIN_VISIBLE = 20


def visible_depths(camera: Camera, xyz: np.ndarray) -> np.ndarray:
    """Camera-space depths z > 0 (world units) of the points xyz (N, 3) that `camera` sees inside its
    image (stg_train.data.visibility.sees; a fisheye's points behind its camera plane have no depth bound)."""
    _, z, seen = sees(camera, xyz)
    return z[seen & (z > 0)]


def bounds_from_points(cameras: Sequence[Camera], xyz: np.ndarray, low: float = LOW_PERCENTILE,
                       high: float = HIGH_PERCENTILE, margin: float = MARGIN,
                       min_visible: int = MIN_VISIBLE) -> np.ndarray | None:
    """(C, 2) float64 near and far depth per camera from 3D points xyz (N, 3) (see the module doc), or
    None when no camera sees min_visible points."""
    per_camera = []
    for cam in cameras:
        z = visible_depths(cam, xyz)
        per_camera.append(None if len(z) < min_visible else
                          (np.percentile(z, low) / margin, np.percentile(z, high) * margin))
    known = [b for b in per_camera if b is not None]
    if not known:
        return None
    fallback = np.median(np.array(known), axis=0)
    return np.array([fallback if b is None else b for b in per_camera], dtype=np.float64)


def model_bounds(rec, cameras: Sequence[Camera]) -> np.ndarray | None:
    """bounds_from_points of a COLMAP model's 3D points (a pycolmap.Reconstruction), or None when it has
    too few."""
    from .colmap import reconstruction_points

    xyz, _ = reconstruction_points(rec)
    return bounds_from_points(cameras, xyz) if len(xyz) else None


def uniform_bounds(num_cameras: int, near: float, far: float) -> np.ndarray:
    """(C, 2) bounds `near`, `far` for every camera; ValueError unless 0 < near < far (finite)."""
    if not (np.isfinite(near) and np.isfinite(far) and 0 < near < far):
        raise ValueError(f"depth bounds must satisfy 0 < near < far, got near {near:g}, far {far:g}")
    return np.tile(np.array([near, far], dtype=np.float64), (num_cameras, 1))


def typical_depth(bounds: np.ndarray | None) -> float | None:
    """The depth at which cameras with near and far bounds (C, 2) see their scene, world units: the
    median over the cameras of the geometric mean of near and far (where a point's picture moves as much
    under a camera's turn by an angle as under a shift of depth x that angle); None without bounds."""
    if bounds is None or len(bounds) == 0:
        return None
    return float(np.median(np.sqrt(np.prod(np.asarray(bounds, np.float64), axis=1))))


def describe(bounds: np.ndarray, source: str) -> str:
    """One line: where the bounds come from and their ranges over the cameras."""
    near, far = np.asarray(bounds)[:, 0], np.asarray(bounds)[:, 1]
    span = lambda v: f"{v.min():.3g}" if np.isclose(v.min(), v.max()) else f"{v.min():.3g}-{v.max():.3g}"  # noqa: E731
    return f"depth bounds from {SOURCES.get(source, source)}: near {span(near)}, far {span(far)}"
