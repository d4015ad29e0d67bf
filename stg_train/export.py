"""Trained parameters -> stg_runtime Model -> `.stg` file, checked against the runtime right away.

The per-Gaussian attributes come from stg_train.raw.to_file_arrays (raw -> file parameters), the
decoder from stg_runtime.onnx_mlp.mlp_to_onnx, the file from stg_runtime.format.save. `export` then
renders the held-out view with the trainer's torch splatter and with the runtime `Player` reading the
written file, and raises ExportMismatch when more of the rgb values differ than the golden tolerance
allows (a few values that differ by more than GOLDEN_MAX only warn: see GOLDEN_MAX).
"""
from __future__ import annotations

import os
import warnings
from dataclasses import dataclass
from typing import NamedTuple
from pathlib import Path

import numpy as np
import torch

import stg_runtime
from stg_runtime import format as stg_format
from stg_runtime.camera import Camera
from stg_runtime.model import Model, Segment
from stg_runtime.onnx_mlp import mlp_to_onnx
from stg_runtime.player import Player

from .params import STGParams
from .raw import to_file_arrays
from .render import rasterize

#: The project's golden-image tolerance between two renders of one model (trainer vs runtime): rgb
#: values may differ by at most GOLDEN_TOLERANCE, except a fraction GOLDEN_FRACTION of them, which may
#: differ by up to GOLDEN_MAX: float32 rounding can flip a threshold decision of the splatting rules
#: (formats/stg-v1.md section 3) at a few pixels, changing them by up to about one 3-sigma-edge contribution.
#: Two Gaussians whose depths are equal to float32 rounding may also be taken in either order, which
#: the spec allows too; that changes a pixel by alpha1 alpha2 (c1 - c2), which no constant bounds. So
#: the export check (`export`) fails only on the fraction, and a file whose few differing values exceed
#: GOLDEN_MAX is kept with an ExportWarning; the golden tests, on scenes without such ties, hold both.
GOLDEN_TOLERANCE = 1e-3
GOLDEN_FRACTION = 1e-3
GOLDEN_MAX = 2e-2


class GoldenDiff(NamedTuple):
    """max_abs: largest |a - b|; fraction_over: share of values with |a - b| > GOLDEN_TOLERANCE."""

    max_abs: float
    fraction_over: float

    @property
    def ok(self) -> bool:
        return self.max_abs <= GOLDEN_MAX and self.fraction_over <= GOLDEN_FRACTION

    @staticmethod
    def of(a: np.ndarray, b: np.ndarray) -> "GoldenDiff":
        diff = np.abs(np.asarray(a, np.float64) - np.asarray(b, np.float64))
        return GoldenDiff(float(diff.max()), float(np.mean(diff > GOLDEN_TOLERANCE)))

    def worst(self, other: "GoldenDiff") -> "GoldenDiff":
        return GoldenDiff(max(self.max_abs, other.max_abs), max(self.fraction_over, other.fraction_over))


class ExportMismatch(RuntimeError):
    """The runtime's render of the exported file disagrees with the trainer's render."""


class ExportWarning(UserWarning):
    """A few values of the runtime's render of the exported file differ from the trainer's by more than
    GOLDEN_MAX (within the fraction the golden tolerance allows)."""


@dataclass
class ExportReport:
    """path of the .stg file; bytes: its size; diff: the worst GoldenDiff of trainer vs runtime rgb over
    the checked views (None when not checked); checked: (camera name, frame) pairs compared."""

    path: Path
    bytes: int
    diff: GoldenDiff | None
    checked: list


def to_model(params: STGParams, cameras: list[Camera], fps: float, num_frames: int, bounds=None,
             provenance: dict | None = None, start_frame: int = 0, context: tuple[int, int] = (0, 0)) -> Model:
    """A one-segment runtime Model of `params` trained on frames [start_frame, start_frame + num_frames).
    context (before, after): that many of those frames at either end were context (Dataset.context_frames):
    the segment then shows the frames between them, over which its time is already normalised (the
    trainer's frame_time), and records the context.

    bounds: ((3,), (3,)) world box; default: the box of the Gaussians' centres. provenance: stored as is
    (tool, version, settings)."""
    arrays = to_file_arrays({k: v.detach().cpu().numpy() for k, v in params.raw.items()})
    decoder = None if params.decoder is None else mlp_to_onnx(params.decoder.weights())
    before, after = (int(c) for c in context)
    segment = Segment(start_frame + before, num_frames - before - after, decoder=decoder, activation="sigmoid",
                      context_frames=(before, after), **arrays)
    if bounds is None:
        xyz = arrays["position"][:, 0]
        bounds = (xyz.min(0).tolist(), xyz.max(0).tolist()) if len(xyz) else ([0.0] * 3, [0.0] * 3)
    return Model(params.kind, fps, [segment], cameras=list(cameras), bounds=bounds,
                 provenance=dict(provenance or {}))


def provenance(settings: dict, **extra) -> dict:
    """{"tool": "stg-train", "version": ..., "settings": settings, **extra} for the file header."""
    return {"tool": "stg-train", "version": stg_runtime.__version__, "settings": settings, **extra}


@torch.no_grad()
def trainer_render(params: STGParams, camera: Camera, tau: float) -> np.ndarray:
    """(H, W, 3) float32 rgb of `params` through the trainer's torch splatter (no gradient)."""
    g = params.at(tau)
    out = rasterize(g.means, g.quats, g.scales, g.opacities, g.features, camera)
    return params.colour(out.features, camera).clamp(0, 1).float().cpu().numpy()


def compare_with_runtime(params: STGParams, player: Player, cameras: list[Camera], frames) -> GoldenDiff:
    """The worst GoldenDiff of trainer rgb vs runtime rgb over every camera x frame j of the player's
    first segment (player at t = (start_frame + j) / fps; the trainer at tau = j / num_frames, its time
    normalised over the segment's shown frames as the file's)."""
    worst = GoldenDiff(0.0, 0.0)
    seg = player.model.segments[0]
    for cam in cameras:
        for j in frames:
            ours = trainer_render(params, cam, j / seg.num_frames)
            theirs = player.render(cam, (seg.start_frame + j) / player.fps)
            worst = worst.worst(GoldenDiff.of(ours, theirs))
    return worst


def export(params: STGParams, path, cameras: list[Camera], fps: float, num_frames: int,
           check_cameras: list[Camera] | None = None, check_frames=None, bounds=None,
           provenance: dict | None = None, start_frame: int = 0, context: tuple[int, int] = (0, 0)) -> ExportReport:
    """Write `params` to `path` (.stg, float32 attributes) as one segment trained on frames
    [start_frame, start_frame + num_frames) of the video, of which the first and last `context` frames
    were context (to_model), then compare the trainer's and the runtime's renders of check_cameras
    (default: none) at check_frames, counted within the segment's shown frames (default: its first,
    middle and last frame). Raises ExportMismatch (the file stays, for inspection) when more than
    GOLDEN_FRACTION of the values differ by over GOLDEN_TOLERANCE; warns (ExportWarning) when fewer do
    but some by over GOLDEN_MAX (see GOLDEN_MAX)."""
    path = Path(path)
    if path.parent and not path.parent.exists():
        os.makedirs(path.parent, exist_ok=True)
    model = to_model(params, cameras, fps, num_frames, bounds, provenance, start_frame=start_frame, context=context)
    stg_format.save(model, path)
    size = path.stat().st_size
    if not check_cameras:
        return ExportReport(path, size, None, [])
    shown = model.segments[0]
    frames = sorted({0, shown.num_frames // 2, shown.num_frames - 1}) if check_frames is None else list(check_frames)
    worst = compare_with_runtime(params, Player(path, device="cpu"), check_cameras, frames)
    checked = [(c.name, shown.start_frame + j) for c in check_cameras for j in frames]
    found = (f"max abs rgb {worst.max_abs:.3g}, {100 * worst.fraction_over:.3g}% of values over "
             f"{GOLDEN_TOLERANCE:g}, over {checked}")
    if worst.fraction_over > GOLDEN_FRACTION:
        raise ExportMismatch(f"{path}: the runtime's render differs from the trainer's ({found}) beyond the "
                             f"golden tolerance (at most {100 * GOLDEN_FRACTION:g}% over {GOLDEN_TOLERANCE:g})")
    if worst.max_abs > GOLDEN_MAX:
        warnings.warn(ExportWarning(
            f"{path}: the runtime's render differs from the trainer's at a few values by more than "
            f"{GOLDEN_MAX:g} ({found}); two Gaussians at equal depths taken in another order can do that "
            f"(formats/stg-v1.md section 3), and the file is kept"))
    return ExportReport(path, size, worst, checked)


def export_trainer(trainer, path, check: bool = True) -> ExportReport:
    """Export a stg_train.trainer.Trainer's current parameters with its dataset's cameras (the training
    cameras' poses refined when the run refines them: Trainer.refined_cameras), fps, frame
    range (start_frame and frame count: a Dataset.frame_range view gives one segment of a longer video)
    and bounds, checked on the dataset's held-out cameras (when `check`)."""
    from dataclasses import asdict

    ds = trainer.dataset
    prov = provenance(asdict(trainer.config), iterations=trainer.step, train_seconds=round(trainer.seconds, 3),
                      data=None if ds.path is None else str(ds.path))
    check_cameras = [ds.cameras[i] for i in ds.test_cameras] if check else None
    return export(trainer.params, path, trainer.refined_cameras(), ds.fps, ds.num_frames, check_cameras=check_cameras,
                  bounds=ds.scene_bounds, provenance=prov, start_frame=getattr(ds, "start_frame", 0),
                  context=getattr(ds, "context_frames", (0, 0)))


def trainer_model(trainer) -> Model:
    """The runtime Model of a Trainer's current parameters, in memory (no file, no check): its
    dataset's cameras, fps, frame range and bounds, as export_trainer writes them. The trainer's
    tensors are copied, never changed."""
    ds = trainer.dataset
    with torch.no_grad():
        return to_model(trainer.params, trainer.refined_cameras(), ds.fps, ds.num_frames, bounds=ds.scene_bounds,
                        start_frame=getattr(ds, "start_frame", 0), context=getattr(ds, "context_frames", (0, 0)))
