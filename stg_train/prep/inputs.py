"""The raw inputs of `stg-prep`: one camera per video file (mp4, mov, mkv, avi, webm, m4v) or per folder
of numbered frames (png, jpg) in one folder, found, probed and checked before anything is written. A
folder that holds only folders (a tree of cameras, such as N3V's frames/) is not a camera and is skipped.

A camera's name is its file's stem (`cam01.mp4` -> `cam01`) or its folder's name. Frames of a folder are
taken in number order (`1.png, 2.png, 10.png`), videos in decoding order. Every problem is a PrepError
whose one-line message starts with the file (or folder) concerned.
"""
from __future__ import annotations

import hashlib
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

from ..data.dataset import DataError
from ..data.frames import DEFAULT_FPS, IMAGE_EXTENSIONS, VIDEO_EXTENSIONS, probe_video, read_image, video_frames

#: Fewer frames than this in a clip (or in the span common to all cameras once synchronised) is refused:
#: the synchronisation needs a signal of some length.
MIN_FRAMES = 8
#: Frame rates that differ by more than this fraction are refused.
FPS_TOLERANCE = 1e-3


class PrepError(DataError):
    """Inputs that cannot be prepared, or a step that failed: one line, starting with the file or camera."""


@dataclass(frozen=True)
class Clip:
    """One camera's raw frames: a video file (`images` None) or a folder of frame files (`images` in
    number order). count: frames; width, height: pixels; fps: the video's frame rate, None for a folder."""

    name: str
    path: Path
    count: int
    width: int
    height: int
    fps: float | None
    images: tuple[Path, ...] | None = None

    def read(self, start: int = 0, count: int | None = None, strict: bool = True) -> Iterator[np.ndarray]:
        """Frames start .. start + count - 1 (default: to the end) as (H, W, 3) uint8 RGB; PrepError naming
        the file when one cannot be decoded or has another size, or, when `strict`, when a video ends
        before them (else the frames stop there: a container may state more frames than it holds)."""
        count = self.count - start if count is None else count
        try:
            if self.images is None:
                frames = video_frames(self.path, count, start)
            else:
                frames = (read_image(p) for p in self.images[start:start + count])
            for k, rgb in enumerate(frames):
                if rgb.shape[:2] != (self.height, self.width):
                    where = self.path if self.images is None else self.images[start + k]
                    raise PrepError(f"{where}: frame {start + k} is {rgb.shape[1]}x{rgb.shape[0]}, the camera's "
                                    f"first frame {self.width}x{self.height}")
                yield rgb
        except PrepError:
            raise
        except DataError as e:
            if strict or self.images is not None:
                raise PrepError(str(e)) from None


def _number_key(path: Path) -> tuple:
    """Sort key of a frame file: the numbers in its name compared as numbers ("2.png" before "10.png")."""
    return tuple(int(p) if p.isdigit() else p for p in re.split(r"(\d+)", path.stem)), path.name


def _frame_files(folder: Path) -> list[Path]:
    files = [p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS]
    return sorted(files, key=_number_key)


def _is_container(folder: Path) -> bool:
    """Whether `folder` holds folders and no frame files: a tree of cameras (N3V's frames/), not one."""
    if not folder.is_dir():
        return False
    entries = [p for p in folder.iterdir() if not p.name.startswith(".")]
    return any(p.is_dir() for p in entries) and not any(p.suffix.lower() in IMAGE_EXTENSIONS for p in entries)


def _probe_folder(folder: Path) -> Clip:
    files = _frame_files(folder)
    if not files:
        raise PrepError(f"{folder}: no frames (png or jpg files) in the camera's folder")
    try:
        h, w = read_image(files[0]).shape[:2]
    except DataError as e:
        raise PrepError(str(e)) from None
    return Clip(folder.name, folder, len(files), w, h, None, tuple(files))


def _probe_video(path: Path) -> Clip:
    try:
        if path.stat().st_size == 0:
            raise PrepError(f"{path}: the file is empty")
        count, w, h, fps = probe_video(path)
    except OSError as e:
        raise PrepError(f"{path}: cannot be read ({e.strerror or e})") from None
    except PrepError:
        raise
    except DataError as e:
        raise PrepError(str(e)) from None
    return Clip(path.stem, path, count, w, h, fps if fps > 0 else None)


def find_clips(folder) -> list[Clip]:
    """The cameras of `folder` (module docstring), ordered by name, probed but not checked against each
    other (check_clips). Other files, and hidden entries, are ignored; a folder that holds a dataset
    layout's cameras (a dataset already) is refused."""
    from ..data.layouts import calibration_file

    root = Path(folder)
    if not root.is_dir():
        raise PrepError(f"{root}: {'is a file, not' if root.exists() else 'no such'} folder of videos")
    if (known := calibration_file(root)) is not None:
        raise PrepError(f"{root}: holds {known}, the cameras of a dataset: stg-train reads it as it is (stg-prep "
                        "takes videos without poses; copy them into a folder of their own to calibrate them)")
    clips: dict[str, Clip] = {}
    for entry in sorted(root.iterdir()):
        if entry.name.startswith("."):
            continue
        if entry.is_dir():
            if _is_container(entry):  # e.g. N3V's frames/camXX beside the videos: not a camera
                continue
            clip = _probe_folder(entry)
        elif entry.suffix.lower() in VIDEO_EXTENSIONS:
            clip = _probe_video(entry)
        else:
            continue
        if clip.name in clips:
            raise PrepError(f"{entry}: a second source for camera {clip.name} (also {clips[clip.name].path.name})")
        clips[clip.name] = clip
    return [clips[n] for n in sorted(clips)]


def check_clips(clips: list[Clip], folder, fps: float | None = None, min_frames: int = MIN_FRAMES) -> float:
    """Check the cameras against each other: at least two, one resolution, one frame rate (a video's,
    else `fps` for frame folders, default 30; `fps` given overrides no video's rate but must agree with
    it), at least min_frames frames each. Returns the frame rate; PrepError naming the files otherwise."""
    if len(clips) < 2:
        found = f"only {clips[0].path.name}" if clips else "none"
        raise PrepError(f"{folder}: needs at least 2 cameras (videos or folders of frames), found {found}")
    first = clips[0]
    for clip in clips[1:]:
        if (clip.width, clip.height) != (first.width, first.height):
            raise PrepError(f"{clip.path}: {clip.width}x{clip.height}, but {first.path} is {first.width}x"
                            f"{first.height}: every camera needs the same resolution")
    rated = [c for c in clips if c.fps is not None]
    for clip in rated[1:]:
        if abs(clip.fps - rated[0].fps) > FPS_TOLERANCE * rated[0].fps:
            raise PrepError(f"{clip.path}: {clip.fps:g} fps, but {rated[0].path} is {rated[0].fps:g} fps: every "
                            "camera needs the same frame rate")
    if rated and fps is not None and abs(fps - rated[0].fps) > FPS_TOLERANCE * rated[0].fps:
        raise PrepError(f"{rated[0].path}: {rated[0].fps:g} fps, but --fps says {fps:g}")
    for clip in clips:
        if clip.count < min_frames:
            raise PrepError(f"{clip.path}: {clip.count} frame{'s' if clip.count != 1 else ''}, too short: every "
                            f"camera needs at least {min_frames}")
    return rated[0].fps if rated else (fps if fps is not None else DEFAULT_FPS)


def source_signature(clips: list[Clip]) -> str:
    """A hex digest of every input file's camera, path, size and modification time: what a prepared
    folder was made from."""
    h = hashlib.sha256()
    for clip in clips:
        for p in (clip.images or (clip.path,)):
            st = p.stat()
            h.update(f"{clip.name}\0{p.resolve()}\0{st.st_size}\0{st.st_mtime_ns}\n".encode())
    return h.hexdigest()[:32]


def is_raw_videos(folder) -> bool:
    """Whether `folder` is stg-prep's input rather than a dataset: a video file or a folder of frames
    directly in it, no layout's cameras (stg_train.data.layouts.calibration_file) and no N3V `frames/`
    folder of camera folders (a Neural 3D Video dataset that lacks its poses, whose error names them)."""
    from ..data.layouts import calibration_file

    root = Path(folder)
    if not root.is_dir() or calibration_file(root) is not None or _is_container(root / "frames"):
        return False
    for entry in root.iterdir():
        if entry.name.startswith("."):
            continue
        if entry.is_file() and entry.suffix.lower() in VIDEO_EXTENSIONS:
            return True
        if entry.is_dir() and any(p.suffix.lower() in IMAGE_EXTENSIONS for p in entry.iterdir()):
            return True
    return False
