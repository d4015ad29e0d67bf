"""Writing rendered frames: PNG sequences (no extra dependency) and mp4 (through OpenCV when installed)."""
from __future__ import annotations

import os
import struct
import zlib
from pathlib import Path

import numpy as np

from .atomic import remove_leftovers, temporary_path, write_atomic

VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv")


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


class FrameWriter:
    """Writes frames to `path`: a video file when it ends in .mp4/.avi/.mov/.mkv (needs OpenCV), else a
    folder of `frame_000000.png` files. A video is written to a temp name and renamed when closed, so
    an interrupted render leaves no half-written file at `path`."""

    def __init__(self, path, fps: float, width: int, height: int):
        self.path = Path(path)
        self.count = 0
        self.video = None
        if self.path.suffix.lower() in VIDEO_SUFFIXES:
            try:
                import cv2
            except ImportError:
                raise RuntimeError(f"{self.path}: writing video needs OpenCV (pip install opencv-python-headless); "
                                   "or give a folder name to write PNG frames") from None
            self.path.parent.mkdir(parents=True, exist_ok=True)
            remove_leftovers(self.path.parent, self.path.name)  # of an interrupted render of this video
            self.tmp = temporary_path(self.path)
            fourcc = cv2.VideoWriter_fourcc(*("mp4v" if self.path.suffix.lower() != ".avi" else "MJPG"))
            self.video = cv2.VideoWriter(str(self.tmp), fourcc, float(fps), (width, height))
            if not self.video.isOpened():
                raise RuntimeError(f"{self.path}: OpenCV cannot open a video writer for this file type")
            self._bgr = lambda rgb: cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
        else:
            self.path.mkdir(parents=True, exist_ok=True)
            remove_leftovers(self.path)  # frames of an interrupted render

    def write(self, image: np.ndarray) -> None:
        """image: (H, W, 3) float32 in [0, 1]."""
        rgb = to_uint8(image)
        if self.video is not None:
            self.video.write(self._bgr(rgb))
        else:
            write_png(self.path / f"frame_{self.count:06d}.png", rgb)
        self.count += 1

    def close(self, ok: bool = True) -> None:
        if self.video is not None:
            self.video.release()
            self.video = None
            if ok:
                os.replace(self.tmp, self.path)
            else:
                self.tmp.unlink(missing_ok=True)
