"""Dataset layouts: the registry of readers, detection, and load_dataset.

    n3v          camXX.mp4 + poses_bounds.npy (Neural 3D Video; stg_train.data.n3v)
    technicolor  <Scene>_undist_<frame>_<cam>.png + cameras_parameters.txt (stg_train.data.technicolor)
    immersive    camera_NNNN.mp4 (or camera_NNNN/ frame folders) + models.json (Google Immersive, fisheye
                 cameras; stg_train.data.immersive)
    reference    colmap_<i>/images/camXX.png + colmap_<i>/sparse/0 (the reference code's preprocessed
                 layout; stg_train.data.reference)
    rig          images/<camera>/<frame>.png or videos/<camera>.mp4 + one COLMAP model sparse/0
                 (custom captures; stg_train.data.rig)

When a folder matches several layouts (the reference code's preprocessing writes colmap_<i> folders
beside the raw N3V or Technicolor files), the raw data wins in the order above; force another with
`layout=`. The layouts are registered in stg_train.choices.LAYOUT_SPECS (reader, detector, what it looks
for), each reader imported when a folder of its layout is read; docs/extending.md adds one.
"""
from __future__ import annotations

import importlib
import re
from pathlib import Path
from typing import Callable

from stg_runtime.progress import progress_callback

from ..choices import LAYOUT_SPECS, LAYOUTS  # noqa: F401 (LAYOUTS re-exported by stg_train.data)
from .bounds import uniform_bounds
from .dataset import DataError, Dataset
from .immersive import MODELS_FILE

_CAM_VIDEO = re.compile(r"^cam\d+\.mp4$")
_CAMERA_VIDEO = re.compile(r"^camera_\d+\.mp4$")
_UNDIST = re.compile(r"^.+_undist_\d+_\d+\.png$")


def _named(root: Path, pattern: re.Pattern) -> bool:
    return any(pattern.match(p.name) for p in root.iterdir())


def looks_like_n3v(root: Path) -> bool:
    return (root / "poses_bounds.npy").is_file() or _named(root, _CAM_VIDEO)


def looks_like_technicolor(root: Path) -> bool:
    return (root / "cameras_parameters.txt").is_file() or _named(root, _UNDIST)


def looks_like_immersive(root: Path) -> bool:
    return (root / MODELS_FILE).is_file() or _named(root, _CAMERA_VIDEO)


def looks_like_reference(root: Path) -> bool:
    return (root / "colmap_0").is_dir()


def looks_like_rig(root: Path) -> bool:
    return (root / "sparse").is_dir() and ((root / "images").is_dir() or (root / "videos").is_dir())


def calibration_file(root: Path) -> str | None:
    """The name of the first layout's cameras that root holds (poses_bounds.npy, cameras_parameters.txt,
    models.json, colmap_0, sparse), else None: videos without them are raw videos for stg-prep
    (stg_train.prep)."""
    for name in ("poses_bounds.npy", "cameras_parameters.txt", MODELS_FILE, "colmap_0", "sparse"):
        if (root / name).exists():
            return name
    return None


def _function(spec: str) -> Callable:
    """The function a "module:function" string of LAYOUT_SPECS names (its module imported now)."""
    module, _, name = spec.partition(":")
    return getattr(importlib.import_module(module), name)


def reader(layout: str) -> Callable[..., Dataset]:
    """The reader of a layout of LAYOUT_SPECS: reader(root, **options) -> Dataset."""
    return _function(LAYOUT_SPECS[layout][0])


def detect_layout(path) -> str:
    """The layout of dataset folder `path`: "n3v", "technicolor", "immersive", "reference" or "rig" (first
    match in that order; LAYOUT_SPECS' detectors). Raises DataError listing what was looked for when
    nothing matches."""
    root = Path(path)
    if not root.is_dir():
        raise DataError(f"{root}: no such directory")
    for name, (_, detector, _) in LAYOUT_SPECS.items():
        if _function(detector)(root):
            return name
    width = max(map(len, LAYOUT_SPECS)) + 2
    raise DataError(f"{root}: not a dataset folder in any known layout; looked for\n" + "\n".join(
        f"  {name + ':':<{width}}{looked_for}" for name, (_, _, looked_for) in LAYOUT_SPECS.items()))


def load_dataset(path, layout: str = "auto", downscale: int = 1, *, cache_dir=None, num_frames: int | None = None,
                 fps: float | None = None, from_video: bool = False, test_camera: str | None = None,
                 depth_range: tuple[float, float] | None = None, progress: Callable[[int, int], None] | None = None,
                 show_progress: bool = False, lazy: bool = False) -> Dataset:
    """Read dataset folder `path` in `layout` ("auto": detect_layout) into a Dataset.

    downscale: integer factor dividing the frames' size and the intrinsics. cache_dir: where decoded
    frames go (default <path>/.stg_cache). num_frames: only the first num_frames frames. fps: frame rate
    (default: the videos' where there are videos, else 30). from_video: read videos even when lossless
    frames exist (n3v, immersive, rig). test_camera: name of the held-out camera (default: cam00 for n3v
    and reference, cam10 for technicolor (else the first), the centre camera for immersive (camera_0001,
    else the most central optical axis), the first camera in sorted order for rig).
    depth_range: (near, far) depth bounds in world units for every camera, replacing the layout's
    (Dataset.bounds_source "user"; ValueError unless 0 < near < far).
    progress: callable(done, total) while frames are decoded; show_progress: without `progress`, a
    progress bar on stderr while they are (nothing is drawn when the frame cache is already there).
    lazy: decode no frame now; frames are decoded into the cache chunk by chunk on their first read
    (stg_train.data.frames.ChunkedFrames, Dataset.chunked), with a bar per chunk when show_progress.
    """
    root = Path(path)
    if layout == "auto":
        layout = detect_layout(root)
    if layout not in LAYOUT_SPECS:
        raise ValueError(f"unknown layout {layout!r}; choose one of auto, {', '.join(LAYOUT_SPECS)}")
    if not root.is_dir():
        raise DataError(f"{root}: no such directory")
    if depth_range is not None:
        uniform_bounds(1, *depth_range)  # checked before any frame is decoded
    options = dict(downscale=downscale, cache_dir=cache_dir, num_frames=num_frames, fps=fps, test_camera=test_camera,
                   lazy=lazy)
    if layout == "n3v":
        options["prefer_png"] = not from_video
    elif layout in ("rig", "immersive"):
        options["from_video"] = from_video
    read = reader(layout)
    if lazy:
        dataset = read(root, **options).chunked(show_progress=show_progress)
    elif progress is not None or not show_progress:
        dataset = read(root, progress=progress, **options)
    else:
        with progress_callback("decode frames") as report:
            dataset = read(root, progress=report, **options)
    if depth_range is not None:
        dataset = dataset.with_bounds(uniform_bounds(dataset.num_cameras, *depth_range), "user")
    return dataset
