"""One data model for every dataset layout: calibrated cameras plus synchronised frames.

Frames are decoded once into a cache file, `frames_uint8.npy`, a uint8 numpy array of shape
(cameras, frames, H, W, 3) (RGB), and read lazily from it as a memory map: a dataset is never loaded into
RAM or onto a GPU as a whole.
"""
from __future__ import annotations

import copy
import json
import os
from pathlib import Path
from typing import Callable, Iterable, Sequence

import numpy as np

from stg_runtime.camera import Camera

CACHE_NAME = "frames_uint8.npy"


class DataError(Exception):
    """A dataset that cannot be read; the message names the file and the problem."""


class Dataset:
    """Cameras and frames of a multi-view video.

    cameras: list[Camera] with names ("cam00", ...); all share one image size (width x height).
    frames: (C, F, H, W, 3) uint8 RGB array-like, normally a read-only np.memmap of the cache file.
    fps: frames per second; frame k is shown at k / fps seconds (`frame_times`).
    test_cameras: indices of held-out cameras; `train_cameras` are the others.
    bounds: (C, 2) float64 near and far depth per camera (world units) when the layout has them, else None.
    scene_bounds: (min (3,), max (3,)) world box when the layout has one, else None.
    start_frame: index in the whole video of this dataset's frame 0 (non-zero for `frame_range` views).
    """

    start_frame = 0

    def __init__(self, cameras: Sequence[Camera], frames, fps: float, test_cameras: Iterable[int] = (),
                 bounds: np.ndarray | None = None, scene_bounds=None, path: str | os.PathLike | None = None):
        self.cameras = list(cameras)
        self.frames = frames
        self.fps = float(fps)
        self.test_cameras = sorted(int(i) for i in test_cameras)
        self.bounds = None if bounds is None else np.asarray(bounds, dtype=np.float64)
        self.scene_bounds = scene_bounds
        self.path = None if path is None else Path(path)
        c, f, h, w, ch = frames.shape
        if c != len(self.cameras) or ch != 3:
            raise ValueError(f"frames of shape {frames.shape} do not match {len(self.cameras)} cameras x RGB")
        for cam in self.cameras:
            if (cam.width, cam.height) != (w, h):
                raise ValueError(f"camera {cam.name}: {cam.width}x{cam.height}, frames are {w}x{h}")
        if any(not 0 <= i < c for i in self.test_cameras):
            raise ValueError(f"test camera index out of range: {self.test_cameras}")

    # -- sizes and times ---------------------------------------------------------------------------
    @property
    def num_cameras(self) -> int:
        return len(self.cameras)

    @property
    def num_frames(self) -> int:
        return int(self.frames.shape[1])

    @property
    def width(self) -> int:
        return int(self.frames.shape[3])

    @property
    def height(self) -> int:
        return int(self.frames.shape[2])

    @property
    def frame_times(self) -> np.ndarray:
        """(F,) float64 seconds of the video at which frame k is shown: (start_frame + k) / fps."""
        return (self.start_frame + np.arange(self.num_frames)) / self.fps

    @property
    def train_cameras(self) -> list[int]:
        return [i for i in range(self.num_cameras) if i not in self.test_cameras]

    def camera_index(self, name: str) -> int:
        """Index of the camera called `name` (KeyError if none)."""
        for i, cam in enumerate(self.cameras):
            if cam.name == name:
                return i
        raise KeyError(f"no camera named {name!r}")

    # -- frames ------------------------------------------------------------------------------------
    def frame(self, camera_index: int, frame_index: int) -> np.ndarray:
        """(H, W, 3) uint8 RGB frame `frame_index` of camera `camera_index` (a copy read from the cache)."""
        if not 0 <= camera_index < self.num_cameras:
            raise IndexError(f"camera index {camera_index} out of range 0..{self.num_cameras - 1}")
        if not 0 <= frame_index < self.num_frames:
            raise IndexError(f"frame index {frame_index} out of range 0..{self.num_frames - 1}")
        return np.array(self.frames[camera_index, frame_index])

    def image(self, camera_index: int, frame_index: int) -> np.ndarray:
        """(H, W, 3) float32 RGB in [0, 1]: `frame` / 255."""
        return self.frame(camera_index, frame_index).astype(np.float32) / 255.0

    def frame_range(self, start: int, count: int) -> "Dataset":
        """A view of frames [start, start + count) (a time segment): same cameras and settings, the
        frames array sliced without copying (a memmap stays a memmap); its frame k is frame start + k
        here, and its start_frame is self.start_frame + start."""
        if not (0 <= start and 0 < count and start + count <= self.num_frames):
            raise IndexError(f"frames {start}..{start + count - 1} are not within 0..{self.num_frames - 1}")
        view = copy.copy(self)
        view.frames = self.frames[:, start:start + count]
        view.start_frame = self.start_frame + int(start)
        return view

    def __repr__(self) -> str:
        return (f"Dataset({self.path or '<memory>'}: {self.num_cameras} cameras x {self.num_frames} frames, "
                f"{self.width}x{self.height}, {self.fps:g} fps, test cameras {self.test_cameras})")


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
    tmp = cache_dir / f"{CACHE_NAME}.{os.getpid()}.tmp"
    try:
        try:
            arr = np.lib.format.open_memmap(tmp, mode="w+", dtype=np.uint8, shape=tuple(shape))
        except OSError as e:
            raise DataError(f"{tmp}: cannot write the frame cache ({e})") from None
        fill(arr)
        arr.flush()
        del arr
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    meta_tmp = meta_path.with_suffix(f".{os.getpid()}.tmp")
    meta_tmp.write_text(json.dumps(wanted, indent=1))
    os.replace(meta_tmp, meta_path)
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
