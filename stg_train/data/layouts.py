"""Dataset layouts: detection, dispatch to the readers, and the frame decoding they share.

    n3v          camXX.mp4 + poses_bounds.npy (Neural 3D Video; stg_train.data.n3v)
    technicolor  <Scene>_undist_<frame>_<cam>.png + cameras_parameters.txt (stg_train.data.technicolor)
    reference    colmap_<i>/images/camXX.png + colmap_<i>/sparse/0 (the reference code's preprocessed
                 layout; stg_train.data.reference)
    rig          images/<camera>/<frame>.png or videos/<camera>.mp4 + one COLMAP model sparse/0
                 (custom captures; stg_train.data.rig)

When a folder matches several layouts (the reference code's preprocessing writes colmap_<i> folders
beside the raw N3V or Technicolor files), the raw data wins in the order above; force another with
`layout=`.
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from stg_runtime.camera import Camera

from .dataset import DataError, Dataset, build_frame_cache, common_frames, file_signature

LAYOUTS = ("n3v", "technicolor", "reference", "rig")
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg")
VIDEO_EXTENSIONS = (".mp4", ".mov", ".avi", ".mkv", ".m4v", ".webm")
DEFAULT_FPS = 30.0
_CAM_VIDEO = re.compile(r"^cam\d+\.mp4$")
_UNDIST = re.compile(r"^.+_undist_\d+_\d+\.png$")


# -- detection and dispatch ------------------------------------------------------------------------
def _looks_like(root: Path) -> dict[str, bool]:
    names = [p.name for p in root.iterdir()]
    sparse = root / "sparse"
    return {
        "n3v": (root / "poses_bounds.npy").is_file() or any(_CAM_VIDEO.match(n) for n in names),
        "technicolor": (root / "cameras_parameters.txt").is_file() or any(_UNDIST.match(n) for n in names),
        "reference": (root / "colmap_0").is_dir(),
        "rig": sparse.is_dir() and ((root / "images").is_dir() or (root / "videos").is_dir()),
    }


def detect_layout(path) -> str:
    """The layout of dataset folder `path`: "n3v", "technicolor", "reference" or "rig" (first match in
    that order). Raises DataError listing what was looked for when nothing matches."""
    root = Path(path)
    if not root.is_dir():
        raise DataError(f"{root}: no such directory")
    found = _looks_like(root)
    for name in LAYOUTS:
        if found[name]:
            return name
    raise DataError(
        f"{root}: not a dataset folder in any known layout; looked for\n"
        "  n3v:         camXX.mp4 videos and poses_bounds.npy\n"
        "  technicolor: <Scene>_undist_<frame>_<cam>.png images and cameras_parameters.txt\n"
        "  reference:   colmap_0/, colmap_1/, ... each with images/camXX.png and sparse/0/\n"
        "  rig:         images/<camera>/<frame>.png (or videos/<camera>.mp4) and a COLMAP model in sparse/0/")


def load_dataset(path, layout: str = "auto", downscale: int = 1, *, cache_dir=None, num_frames: int | None = None,
                 fps: float | None = None, from_video: bool = False, test_camera: str | None = None,
                 progress: Callable[[int, int], None] | None = None) -> Dataset:
    """Read dataset folder `path` in `layout` ("auto": detect_layout) into a Dataset.

    downscale: integer factor dividing the frames' size and the intrinsics. cache_dir: where decoded
    frames go (default <path>/.stg_cache). num_frames: only the first num_frames frames. fps: frame rate
    (default: the videos' where there are videos, else 30). from_video: read videos even when lossless
    frames exist (n3v, rig). test_camera: name of the held-out camera (default: cam00 for n3v and
    reference, cam10 for technicolor (else the first), the first camera in sorted order for rig).
    progress: callable(done, total) while frames are decoded.
    """
    root = Path(path)
    if layout == "auto":
        layout = detect_layout(root)
    if layout not in LAYOUTS:
        raise ValueError(f"unknown layout {layout!r}; choose one of auto, {', '.join(LAYOUTS)}")
    if not root.is_dir():
        raise DataError(f"{root}: no such directory")
    common = dict(downscale=downscale, cache_dir=cache_dir, num_frames=num_frames, fps=fps, progress=progress)
    if layout == "n3v":
        from .n3v import load_n3v

        data = load_n3v(root, prefer_png=not from_video, **common)
        if test_camera is not None:
            names = [c.name for c in data.cameras]
            if test_camera not in names:
                raise DataError(f"{root}: no camera named {test_camera!r} to hold out (cameras: {', '.join(names)})")
            data.test_cameras = [names.index(test_camera)]
        return data
    if layout == "technicolor":
        from .technicolor import load_technicolor as reader
    elif layout == "reference":
        from .reference import load_reference as reader
    else:
        from .rig import load_rig

        return load_rig(root, from_video=from_video, test_camera=test_camera, **common)
    return reader(root, test_camera=test_camera, **common)


# -- frames shared by the readers ------------------------------------------------------------------
@dataclass
class FrameSource:
    """The frames of one camera: a sorted list of image files, or one video file."""

    images: list[Path] | None = None
    video: Path | None = None

    @property
    def path(self) -> Path:
        return self.video if self.video is not None else self.images[0].parent

    @property
    def files(self) -> list[Path]:
        return [self.video] if self.video is not None else list(self.images)


def image_files(folder: Path) -> list[Path]:
    """Image files (png, jpg) directly in `folder`, sorted by name."""
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS)


def read_image(path: Path) -> np.ndarray:
    """(H, W, 3) uint8 RGB, or DataError naming the file."""
    from .n3v import _read_png

    return _read_png(Path(path))


def probe(source: FrameSource) -> tuple[int, int, int, float | None]:
    """(frame count, width, height, fps or None) of one camera's frames."""
    if source.video is not None:
        from .n3v import _probe_video

        count, w, h, fps = _probe_video(source.video)
        return count, w, h, (fps if fps > 0 else None)
    h, w = read_image(source.images[0]).shape[:2]
    return len(source.images), w, h, None


def _resize(rgb: np.ndarray, width: int, height: int) -> np.ndarray:
    import cv2

    return cv2.resize(rgb, (width, height), interpolation=cv2.INTER_AREA)


def _decode(source: FrameSource, num_frames: int):
    """(label, frame) pairs of the first num_frames frames."""
    if source.video is not None:
        from .n3v import _video_frames

        for k, rgb in enumerate(_video_frames(source.video, num_frames)):
            yield f"{source.video} frame {k}", rgb
    else:
        for f in source.images[:num_frames]:
            yield str(f), read_image(f)


def build_dataset(root: Path, layout: str, cameras: Sequence[Camera], sources: Sequence[FrameSource], *,
                  test_camera: str, downscale: int = 1, cache_dir=None, num_frames: int | None = None,
                  fps: float | None = None, progress=None, signature: dict | None = None,
                  check: Callable[[], None] | None = None) -> Dataset:
    """A Dataset from full-resolution cameras and their frame sources (same order), frames decoded into
    the frame cache <cache_dir or root/.stg_cache>/<layout>_<kind>_x<downscale>_f<num_frames>.

    Checks that every camera has the same number of frames (or at least num_frames) and that frames
    and cameras have one size, raising DataError naming the file. fps: used when given, else the first
    video's, else 30. signature: extra JSON-able cache key (e.g. calibration files). check: called
    before frames are decoded into a new cache (for costly consistency checks).
    """
    if int(downscale) != downscale or downscale < 1:
        raise ValueError(f"downscale must be a positive integer, got {downscale}")
    downscale = int(downscale)
    names = [c.name for c in cameras]
    if test_camera not in names:
        raise DataError(f"{root}: no camera named {test_camera!r} to hold out (cameras: {', '.join(names)})")
    probes = [probe(s) for s in sources]
    labels = [str(s.path.relative_to(root)) if s.path.is_relative_to(root) else str(s.path) for s in sources]
    num_frames, width, height = common_frames(root, [s.path for s in sources], labels,
                                              [c for c, _, _, _ in probes], [(w, h) for _, w, h, _ in probes],
                                              num_frames)
    for cam, src in zip(cameras, sources):
        if (cam.width, cam.height) != (width, height):
            raise DataError(f"{src.path}: frames are {width}x{height} but camera {cam.name} is calibrated for "
                            f"{cam.width}x{cam.height}")
    out_w, out_h = width // downscale, height // downscale
    if out_w < 1 or out_h < 1:
        raise ValueError(f"downscale {downscale} leaves no pixels of {width}x{height} frames")
    scaled = [Camera(c.fx / downscale, c.fy / downscale, c.cx / downscale, c.cy / downscale, out_w, out_h,
                     c.world_to_camera, c.name) for c in cameras]
    if fps is None:
        fps = next((f for _, _, _, f in probes if f), None)
    fps = DEFAULT_FPS if fps is None else float(fps)
    if not fps > 0:
        raise ValueError(f"fps must be positive, got {fps}")

    kind = "video" if sources[0].video is not None else "images"
    files = [f for s in sources for f in (s.files if s.video is not None else s.images[:num_frames])]
    key = {"layout": layout, "source": kind, "downscale": downscale, "num_frames": num_frames,
           "files": [[str(Path(p).relative_to(root)) if Path(p).is_relative_to(root) else p, size, mtime]
                     for p, size, mtime in file_signature(files)], **(signature or {})}
    shape = (len(scaled), num_frames, out_h, out_w, 3)

    def fill(arr: np.ndarray) -> None:
        if check is not None:
            check()
        total, done = len(sources) * num_frames, 0
        for ci, src in enumerate(sources):
            for k, (label, rgb) in enumerate(_decode(src, num_frames)):
                if rgb.shape[:2] != (height, width):
                    raise DataError(f"{label}: is {rgb.shape[1]}x{rgb.shape[0]}, expected {width}x{height}")
                arr[ci, k] = _resize(rgb, out_w, out_h) if downscale > 1 else rgb
                done += 1
                if progress is not None:
                    progress(done, total)

    cache_root = Path(cache_dir) if cache_dir is not None else root / ".stg_cache"
    frames = build_frame_cache(cache_root / f"{layout}_{kind}_x{downscale}_f{num_frames}", key, shape, fill)
    return Dataset(scaled, frames, fps, test_cameras=[names.index(test_camera)], path=root)
