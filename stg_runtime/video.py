"""Writing rendered frames: a folder of PNGs (no extra dependency) or a video file through PyAV (the
`video` extra: its wheels carry FFmpeg with the codecs).

    output_kind(path)         "folder" or the video suffix; ValueError for a name that is neither
    FrameWriter(path, ...)    writes frames one by one, atomically

Video files, by suffix (docs/render.md):

    .mp4 .mov .mkv   H.264 (libx264), yuv420p: what every browser and player plays
    .webm            VP9 (libvpx-vp9), yuv420p
    .gif             GIF, 8-bit colour (3-3-2), for previews

A name without a suffix, one ending in a path separator, or an existing folder receives PNG frames
`frame_000000.png`, ... . Any other suffix is refused. yuv420p needs an even width and height: an odd
one is cropped by its last column or row, with a VideoSizeWarning saying so.
"""
from __future__ import annotations

import os
import struct
import warnings
import zlib
from pathlib import Path

import numpy as np

from .atomic import remove_leftovers, temporary_path, write_atomic

#: Video suffix -> (FFmpeg encoder, pixel format).
VIDEO_CODECS = {".mp4": ("libx264", "yuv420p"), ".mov": ("libx264", "yuv420p"), ".mkv": ("libx264", "yuv420p"),
                ".webm": ("libvpx-vp9", "yuv420p"), ".gif": ("gif", "rgb8")}
VIDEO_SUFFIXES = tuple(VIDEO_CODECS)
_SUFFIX_LIST = ".mp4, .mov, .mkv (H.264), .webm (VP9) or .gif"


class VideoSizeWarning(UserWarning):
    """A frame size the codec cannot take was cropped (yuv420p: even sizes)."""


def to_uint8(image: np.ndarray) -> np.ndarray:
    """(H, W, 3) float in [0, 1] -> uint8, rounded."""
    return (np.clip(image, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def write_png(path, image: np.ndarray) -> None:
    """Write an (H, W, 3) uint8 RGB image as an 8-bit PNG (atomically: temp file + rename)."""
    write_atomic(path, encode_png(image))


def encode_png(image: np.ndarray) -> bytes:
    """The bytes of an 8-bit PNG of an (H, W, 3) uint8 RGB image."""
    image = np.ascontiguousarray(image, dtype=np.uint8)
    h, w, c = image.shape
    if c != 3:
        raise ValueError(f"write_png: expected (H, W, 3), got {image.shape}")
    raw = np.concatenate([np.zeros((h, 1), np.uint8), image.reshape(h, w * 3)], axis=1).tobytes()

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(raw, 6)) + chunk(b"IEND", b""))


def output_kind(path) -> str:
    """"folder" (PNG frames) or the lower-case video suffix of `path`; ValueError naming the path when
    it is neither (an unknown suffix, a video name that is a folder, a folder name that is a file, a
    parent that is a file)."""
    text = os.fspath(path)
    p = Path(text)
    suffix = p.suffix.lower()
    folder = text.endswith(("/", os.sep)) or p.is_dir() or not suffix
    if folder:
        if p.exists() and not p.is_dir():
            raise ValueError(f"{text}: is a file, not a folder for PNG frames (name a folder, or a video ending in "
                             f"{_SUFFIX_LIST})")
        kind = "folder"
    elif suffix not in VIDEO_CODECS:
        raise ValueError(f"{text}: unknown video type {suffix!r}: name a video ending in {_SUFFIX_LIST}, or a "
                         "folder (no suffix, or ending in /) for PNG frames")
    else:
        kind = suffix
    for parent in p.parents if kind != "folder" else (p, *p.parents):
        if parent.exists():
            if not parent.is_dir():
                raise ValueError(f"{text}: cannot write: {parent} is a file, not a folder")
            break
    return kind


def encoded_size(kind: str, width: int, height: int) -> tuple[int, int]:
    """The frame size a video of `kind` (output_kind) stores for width x height frames: even for yuv420p."""
    if kind != "folder" and VIDEO_CODECS[kind][1] == "yuv420p":
        return width - width % 2, height - height % 2
    return width, height


def _open_av():
    try:
        import av
    except ImportError:
        raise RuntimeError("writing a video needs PyAV: python -m pip install av (or the `video` extra); "
                           "or give a folder name to write PNG frames") from None
    return av


class FrameWriter:
    """Writes (H, W, 3) float frames to `path` (see the module doc for the kinds). A video is written to
    a temporary name and renamed when closed with ok=True, so an interrupted render leaves no
    half-written file at `path`; PNG frames are each written atomically."""

    def __init__(self, path, fps: float, width: int, height: int):
        self.kind = output_kind(path)
        self.path = Path(path)
        self.count = 0
        self.container = None
        self.size = encoded_size(self.kind, width, height)
        if self.kind == "folder":
            self.path.mkdir(parents=True, exist_ok=True)
            remove_leftovers(self.path)  # frames of an interrupted render
            return
        if not (fps > 0 and np.isfinite(fps)):
            raise ValueError(f"{self.path}: frames per second must be positive, got {fps}")
        if min(self.size) < 1:
            raise ValueError(f"{self.path}: a {width}x{height} frame is too small for {self.kind} video")
        if self.size != (width, height):
            warnings.warn(f"{self.path}: {self.kind} video (H.264/VP9, yuv420p) needs an even width and height: "
                          f"the {width}x{height} frames are stored as {self.size[0]}x{self.size[1]} (last "
                          f"{'column' if self.size[0] != width else 'row'}{' and row' if self.size[0] != width and self.size[1] != height else ''} cropped)",
                          VideoSizeWarning, stacklevel=3)
        av = _open_av()
        from fractions import Fraction

        self.path.parent.mkdir(parents=True, exist_ok=True)
        remove_leftovers(self.path.parent, self.path.name)  # of an interrupted render of this video
        self.tmp = temporary_path(self.path)
        codec, pix_fmt = VIDEO_CODECS[self.kind]
        # mp4 / mov: the index (moov) first, so a browser starts playing before the whole file is loaded
        options = {"movflags": "+faststart"} if self.kind in (".mp4", ".mov") else {}
        self.container = av.open(str(self.tmp), "w", options=options)
        try:
            self.stream = self.container.add_stream(codec, rate=Fraction(fps).limit_denominator(1001))
            self.stream.width, self.stream.height = self.size
            self.stream.pix_fmt = pix_fmt
            if codec == "libx264":
                self.stream.options = {"crf": "18"}
        except Exception:
            self.container.close()
            self.tmp.unlink(missing_ok=True)
            raise
        self._av = av

    def write(self, image: np.ndarray) -> None:
        """image: (H, W, 3) float32 in [0, 1]."""
        rgb = to_uint8(image)
        if self.container is not None:
            w, h = self.size
            frame = self._av.VideoFrame.from_ndarray(np.ascontiguousarray(rgb[:h, :w]), format="rgb24")
            for packet in self.stream.encode(frame):
                self.container.mux(packet)
        else:
            write_png(self.path / f"frame_{self.count:06d}.png", rgb)
        self.count += 1

    def close(self, ok: bool = True) -> None:
        """Finish the file (ok) or drop it (not ok: nothing is left at path)."""
        if self.container is None:
            return
        try:
            if ok:
                for packet in self.stream.encode():
                    self.container.mux(packet)
        finally:
            self.container.close()
            self.container = None
        if ok:
            os.replace(self.tmp, self.path)
        else:
            self.tmp.unlink(missing_ok=True)
