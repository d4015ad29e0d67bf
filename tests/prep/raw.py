"""Raw-video folders for the stg-prep tests, made from synthetic N3V scenes (stg_train.synthetic) with the
poses thrown away: each camera's lossless frames, its first `cuts[c]` frames left out (a camera that
started recording that many frames late), as a folder of PNG frames or an mp4 video."""
from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np


def raw_folder(n3v: Path, out: Path, cuts=None, kind: str = "png", frames: int | None = None) -> Path:
    """out/<camera>/<k>.png (kind "png") or out/<camera>.mp4 (kind "mp4") for every camera of the N3V
    folder n3v, frames cuts[c] .. of camera c (at most `frames` of them)."""
    out.mkdir(parents=True, exist_ok=True)
    folders = sorted((n3v / "frames").iterdir())
    cuts = [0] * len(folders) if cuts is None else list(cuts)
    for folder, cut in zip(folders, cuts):
        files = sorted(folder.glob("*.png"))[cut:]
        files = files[:frames] if frames is not None else files
        if kind == "png":
            (out / folder.name).mkdir()
            for k, f in enumerate(files):
                shutil.copyfile(f, out / folder.name / f"{k}.png")
        else:
            first = cv2.imread(str(files[0]))
            writer = cv2.VideoWriter(str(out / f"{folder.name}.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 30.0,
                                     (first.shape[1], first.shape[0]))
            for f in files:
                writer.write(cv2.imread(str(f)))
            writer.release()
    return out


def write_video(path: Path, frames: int, size=(64, 48), fps: float = 30.0, seed: int = 0) -> Path:
    """A small mp4 of random frames (for the input checks, which never look at the pictures)."""
    rng = np.random.default_rng(seed)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, size)
    for _ in range(frames):
        writer.write(rng.integers(0, 256, (size[1], size[0], 3), dtype=np.uint8))
    writer.release()
    return path
