"""One data model for every dataset layout: calibrated cameras plus synchronised frames.

Frames are read lazily from a uint8 array (normally the memory-mapped frame cache that
stg_train.data.frames builds): a dataset is never loaded into RAM or onto a GPU as a whole.
"""
from __future__ import annotations

import copy
import os
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from stg_runtime.camera import Camera


class DataError(Exception):
    """A dataset that cannot be read; the message names the file and the problem."""


class Dataset:
    """Cameras and frames of a multi-view video.

    cameras: list[Camera] with names ("cam00", ...); all share one image size (width x height).
    frames: (C, F, H, W, 3) uint8 RGB array-like, normally a read-only np.memmap of the cache file.
    fps: frames per second; frame k is shown at k / fps seconds (`frame_times`).
    test_cameras: indices of held-out cameras; `train_cameras` are the others.
    bounds: (C, 2) float64 near and far depth per camera (world units) when known, else None.
    bounds_source: where the bounds come from (stg_train.data.bounds.SOURCES: "layout", "colmap", "user",
    "sfm"), None without bounds.
    scene_bounds: (min (3,), max (3,)) world box when the layout has one, else None.
    start_frame: index in the whole video of this dataset's frame 0 (non-zero for `frame_range` views).
    context_frames: (before, after): of this dataset's frames, how many at its start and at its end are
    context, fitted to but not shown (a segment's neighbouring frames, stg_train.segments); the frames
    shown are `shown()`.
    """

    start_frame = 0
    context_frames = (0, 0)
    brightness: dict | None = None  # see `corrected`

    def __init__(self, cameras: Sequence[Camera], frames, fps: float, test_cameras: Iterable[int] = (),
                 bounds: np.ndarray | None = None, scene_bounds=None, path: str | os.PathLike | None = None,
                 bounds_source: str | None = None):
        self.cameras = list(cameras)
        self.frames = frames
        self.fps = float(fps)
        self.test_cameras = sorted(int(i) for i in test_cameras)
        self.bounds = None if bounds is None else np.asarray(bounds, dtype=np.float64)
        self.bounds_source = None if bounds is None else (bounds_source or "layout")
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
        if self.bounds is not None and self.bounds.shape != (c, 2):
            raise ValueError(f"bounds of shape {self.bounds.shape} do not match {c} cameras x (near, far)")

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
        """(H, W, 3) float32 RGB in [0, 1]: `frame` / 255 (in a `corrected` view, divided by the camera's
        brightness and clipped to [0, 1])."""
        image = self.frame(camera_index, frame_index).astype(np.float32) / 255.0
        brightness = None if self.brightness is None else self.brightness.get(camera_index)
        return image if brightness is None else np.clip(image / brightness, 0.0, 1.0)

    def frame_range(self, start: int, count: int, context: tuple[int, int] = (0, 0)) -> "Dataset":
        """A view of frames [start, start + count) (a time segment): same cameras and settings, the
        frames array sliced without copying (a memmap stays a memmap); its frame k is frame start + k
        here, and its start_frame is self.start_frame + start. context (before, after): the view also
        holds that many frames before and after as context (its context_frames; it then starts
        `before` frames earlier)."""
        before, after = (int(c) for c in context)
        first, end = start - before, start + count + after
        if not (0 <= first and 0 < count and min(before, after) >= 0 and end <= self.num_frames):
            raise IndexError(f"frames {first}..{end - 1} are not within 0..{self.num_frames - 1}")
        view = copy.copy(self)
        view.frames = self.frames[:, first:end]
        view.start_frame = self.start_frame + int(first)
        view.context_frames = (before, after)
        return view

    def shown(self) -> "Dataset":
        """This dataset without its context frames (itself when it has none)."""
        before, after = self.context_frames
        if not before and not after:
            return self
        return self.frame_range(before, self.num_frames - before - after)

    def with_bounds(self, bounds: np.ndarray, source: str) -> "Dataset":
        """A view with near/far depth bounds (C, 2) from `source` (see bounds_source); the frames are
        shared, this dataset is left as it is."""
        bounds = np.asarray(bounds, dtype=np.float64)
        if bounds.shape != (self.num_cameras, 2):
            raise ValueError(f"bounds of shape {bounds.shape} do not match {self.num_cameras} cameras x (near, far)")
        view = copy.copy(self)
        view.bounds, view.bounds_source = bounds, source
        return view

    def with_cameras(self, cameras: Sequence[Camera]) -> "Dataset":
        """A view with these cameras in place of its own (as many, the same sizes: a pose aligned or
        refined); the frames are shared, this dataset is left as it is."""
        cameras = list(cameras)
        if len(cameras) != self.num_cameras or any((c.width, c.height) != (self.width, self.height) for c in cameras):
            raise ValueError(f"with_cameras: {len(cameras)} cameras for a dataset of {self.num_cameras} "
                             f"at {self.width}x{self.height}")
        view = copy.copy(self)
        view.cameras = cameras
        return view

    def corrected(self, brightness: dict) -> "Dataset":
        """A view whose `image` of camera c is divided by brightness[c] ((H, W, 3) or (3,) float32: the
        camera's lens falloff times its colour gains, stg_train.rig.lens.picture_brightness), so that its
        pictures agree with each other as the canonical scene would (cameras not in `brightness` as they
        are); `frame` still gives the pictures as captured. This dataset is left as it is."""
        view = copy.copy(self)
        view.brightness = {int(c): np.asarray(b, np.float32) for c, b in brightness.items()}
        return view

    def chunked(self, spans=None, show_progress: bool | None = None) -> "Dataset":
        """This dataset with its lazily decoded frames (load_dataset(lazy=True)) cut into frame-cache
        chunks at `spans` ((start, count) pairs covering every frame in order, e.g. the segments of
        stg_train.segments.plan_segments), so that a segment's frame_range view decodes only its own
        frames; show_progress switches the chunks' decoding bars on or off. A dataset whose frames are
        an array is returned as it is."""
        if not hasattr(self.frames, "with_options"):
            return self
        view = copy.copy(self)
        view.frames = self.frames.with_options(None if spans is None else [tuple(s)[-2:] for s in spans],
                                               show_progress)
        return view

    def __repr__(self) -> str:
        return (f"Dataset({self.path or '<memory>'}: {self.num_cameras} cameras x {self.num_frames} frames, "
                f"{self.width}x{self.height}, {self.fps:g} fps, test cameras {self.test_cameras})")
