"""Frames on disk -> the frame cache: frame sources (image files or a video per camera), readers,
probing, and build_dataset, which every layout reader ends with.

Frames are decoded once into a cache file, `frames_uint8.npy`, a uint8 numpy array of shape
(cameras, frames, H, W, 3) (RGB) under <dataset>/.stg_cache/, rebuilt only when the source files or
options change, and read lazily from it as a memory map.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable, Sequence

import numpy as np

from stg_runtime.atomic import atomic_output, remove_leftovers, write_atomic
from stg_runtime.camera import Camera

from .dataset import DataError, Dataset

CACHE_NAME = "frames_uint8.npy"
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg")
VIDEO_EXTENSIONS = (".mp4", ".mov", ".avi", ".mkv", ".m4v", ".webm")
#: Frames per second of layouts that store none.
DEFAULT_FPS = 30.0


# -- reading one camera's frames -------------------------------------------------------------------
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
    """(H, W, 3) uint8 RGB of an image file (png, jpg), or DataError naming the file."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        _check_readable(path)
        raise DataError(f"{path}: cannot be read as an image")
    return img[..., ::-1]


def _check_readable(path: Path) -> None:
    """DataError saying why when `path` cannot be opened at all (OpenCV only says that it failed)."""
    try:
        with open(path, "rb"):
            pass
    except OSError as e:
        raise DataError(f"{path}: cannot be read ({e.strerror or e})") from None


def probe_video(path: Path) -> tuple[int, int, int, float]:
    """(frame count, width, height, fps) of a video, or DataError."""
    import cv2

    cap = cv2.VideoCapture(str(path))
    try:
        if not cap.isOpened():
            _check_readable(path)
            raise DataError(f"{path}: cannot be opened as a video")
        count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        width, height = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        fps = float(cap.get(cv2.CAP_PROP_FPS))
        if count <= 0:  # no frame count in the container: count by decoding
            count = 0
            while cap.grab():
                count += 1
        if count <= 0 or width <= 0 or height <= 0:
            raise DataError(f"{path}: the video has zero frames")
        return count, width, height, fps
    finally:
        cap.release()


def video_frames(path: Path, num_frames: int):
    """The first num_frames frames of a video as (H, W, 3) uint8 RGB; DataError if it has fewer."""
    import cv2

    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise DataError(f"{path}: cannot be opened as a video")
    try:
        for k in range(num_frames):
            ok, bgr = cap.read()
            if not ok or bgr is None:
                raise DataError(f"{path}: decoded only {k} of {num_frames} frames")
            yield np.ascontiguousarray(bgr[..., ::-1])
    finally:
        cap.release()


def probe(source: FrameSource) -> tuple[int, int, int, float | None]:
    """(frame count, width, height, fps or None) of one camera's frames."""
    if source.video is not None:
        count, w, h, fps = probe_video(source.video)
        return count, w, h, (fps if fps > 0 else None)
    h, w = read_image(source.images[0]).shape[:2]
    return len(source.images), w, h, None


def resize(rgb: np.ndarray, width: int, height: int) -> np.ndarray:
    """rgb (H, W, 3) resized to width x height by area averaging (OpenCV's INTER_AREA)."""
    import cv2

    return cv2.resize(rgb, (width, height), interpolation=cv2.INTER_AREA)


def _decode(source: FrameSource, num_frames: int):
    """(label, frame) pairs of the first num_frames frames."""
    if source.video is not None:
        for k, rgb in enumerate(video_frames(source.video, num_frames)):
            yield f"{source.video} frame {k}", rgb
    else:
        for f in source.images[:num_frames]:
            yield str(f), read_image(f)


# -- the frame cache -------------------------------------------------------------------------------
def build_frame_cache(cache_dir, signature: dict, shape: tuple, fill: Callable[[np.ndarray], None]) -> np.memmap:
    """Open the frame cache in cache_dir, (re)building it when it is missing or was made from other data.

    signature: JSON-able description of the source (files, sizes, modification times, options); the
    cache is reused only when it matches. shape: (C, F, H, W, 3). fill(array): writes every frame into
    the writable memmap it is given. The file is written under a temporary name and renamed when
    complete, so an interrupted build is never taken for a cache. Returns a read-only memmap.
    """
    cache_dir = Path(cache_dir)
    path, meta_path = cache_dir / CACHE_NAME, cache_dir / "frames_uint8.json"
    wanted = dict(signature, shape=list(shape))
    if path.exists() and meta_path.exists():
        try:
            if json.loads(meta_path.read_text()) == wanted:
                arr = np.load(path, mmap_mode="r")
                if arr.shape == tuple(shape) and arr.dtype == np.uint8:
                    return arr
        except (OSError, ValueError):
            pass
    try:
        cache_dir.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise DataError(f"{cache_dir}: cannot create the frame cache folder ({e})") from None
    remove_leftovers(cache_dir, CACHE_NAME)  # of an interrupted build
    with atomic_output(path) as tmp:
        try:
            arr = np.lib.format.open_memmap(tmp, mode="w+", dtype=np.uint8, shape=tuple(shape))
        except OSError as e:
            raise DataError(f"{tmp}: cannot write the frame cache ({e})") from None
        fill(arr)
        arr.flush()
        del arr
    write_atomic(meta_path, json.dumps(wanted, indent=1))
    return np.load(path, mmap_mode="r")


def common_frames(root, paths, labels, counts, sizes, num_frames: int | None = None) -> tuple[int, int, int]:
    """(num_frames, width, height) shared by every camera's frame source, or DataError naming the file.

    paths: each source's file or folder; labels: their short names (for listings); counts: their frame
    counts; sizes: their (width, height). Without num_frames all counts must be equal; with it, every
    source needs at least that many frames.
    """
    if num_frames is None:
        if len(set(counts)) > 1:
            listing = ", ".join(f"{lab}: {c} frames" for lab, c in zip(labels, counts))
            raise DataError(f"{root}: cameras have different frame counts ({listing}); pass num_frames to use "
                            f"the first {min(counts)}")
        num_frames = counts[0]
    else:
        short = [(path, c) for path, c in zip(paths, counts) if c < num_frames]
        if short:
            raise DataError(f"{short[0][0]}: has {short[0][1]} frames, fewer than the {num_frames} asked for")
    if len(set(sizes)) > 1:
        listing = ", ".join(f"{lab}: {w}x{h}" for lab, (w, h) in zip(labels, sizes))
        raise DataError(f"{root}: cameras have different frame sizes ({listing})")
    return num_frames, *sizes[0]


def file_signature(paths: Iterable[Path]) -> list:
    """[name, size, mtime_ns] of each file, for cache validation."""
    out = []
    for p in paths:
        st = Path(p).stat()
        out.append([str(p), st.st_size, st.st_mtime_ns])
    return out


def build_dataset(root: Path, layout: str, cameras: Sequence[Camera] | Callable[[int, int], Sequence[Camera]],
                  sources: Sequence[FrameSource], *, test_camera: str, downscale: int = 1, cache_dir=None,
                  num_frames: int | None = None, fps: float | None = None, default_fps: float = DEFAULT_FPS,
                  bounds=None, bounds_source: str = "layout", progress=None, signature: dict | None = None,
                  check: Callable[[], None] | None = None) -> Dataset:
    """A Dataset from full-resolution cameras and their frame sources (same order), frames decoded into
    the frame cache <cache_dir or root/.stg_cache>/<layout>_<kind>_x<downscale>_f<num_frames>.

    cameras: the cameras, or a function of the frames' (width, height) that makes them (for layouts
    whose calibration is relative to the image size). Checks that every camera has the same number of
    frames (or at least num_frames) and that frames and cameras have one size, raising DataError naming
    the file. fps: used when given, else the first video's, else default_fps. bounds: (C, 2) near and
    far depth per camera, when the layout has them; bounds_source: where they come from (Dataset.bounds_source).
    signature: extra JSON-able cache key (e.g.
    calibration files). check: called before frames are decoded into a new cache (for costly
    consistency checks). progress(done, total): called per decoded frame.
    """
    if int(downscale) != downscale or downscale < 1:
        raise ValueError(f"downscale must be a positive integer, got {downscale}")
    downscale = int(downscale)
    probes = [probe(s) for s in sources]
    labels = [str(s.path.relative_to(root)) if s.path.is_relative_to(root) else str(s.path) for s in sources]
    num_frames, width, height = common_frames(root, [s.path for s in sources], labels,
                                              [c for c, _, _, _ in probes], [(w, h) for _, w, h, _ in probes],
                                              num_frames)
    if callable(cameras):
        cameras = cameras(width, height)
    names = [c.name for c in cameras]
    if test_camera not in names:
        raise DataError(f"{root}: no camera named {test_camera!r} to hold out (cameras: {', '.join(names)})")
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
    fps = default_fps if fps is None else float(fps)
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
                arr[ci, k] = resize(rgb, out_w, out_h) if downscale > 1 else rgb
                done += 1
                if progress is not None:
                    progress(done, total)

    cache_root = Path(cache_dir) if cache_dir is not None else root / ".stg_cache"
    frames = build_frame_cache(cache_root / f"{layout}_{kind}_x{downscale}_f{num_frames}", key, shape, fill)
    return Dataset(scaled, frames, fps, test_cameras=[names.index(test_camera)], bounds=bounds, path=root,
                   bounds_source=bounds_source)
