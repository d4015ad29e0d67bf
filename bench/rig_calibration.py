#!/usr/bin/env python
"""What the rig's measurement before training finds and decides (stg_train.rig.self_calibration.calibrate_rig,
TrainConfig's lens_falloff, appearance and pose_refine "auto"), on synthetic captures whose truth is
known: the demo scene's 12 cameras at 160x120, 2 frames, captured cleanly, through `stg-synth
--realistic`'s defaults (two seeds), with the pose error alone, with the vignetting alone, and cleanly
with 30 % vignetting on every other lens or on one; and the scene's outward-facing dome rig of 12
fisheye or pinhole cameras of 120 degrees (`stg-synth --fisheye 120`, `--pinhole-dome 120`).

    python bench/rig_calibration.py [--data DIR] [--json PATH]

Prints per capture: the rig's corner brightness (1 + K1 + K2; 1 is no falloff), each camera's own, the
spread of the cameras' colour gains (RMS of their logs), the matches' median distance from the stated
poses' epipolar lines, the seconds the measurement took, and what was decided (the falloff trained
with, or none; whether a per-camera appearance is learned; whether the poses are refined).
"""
from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import stg_train  # noqa: F401  (first: it configures OpenMP before torch loads)
import numpy as np

from stg_train.rig.capture import CaptureModel, with_vignetting
from stg_train.config import TrainConfig
from stg_train.data import load_dataset, load_n3v
from stg_train.data.dataset import Dataset
from stg_train.rig.self_calibration import calibrate_rig
from stg_train.synthetic import SyntheticScene, write_immersive, write_n3v

VIGNETTING_ALONE = dict(gain=0, white_balance=0, noise=0, rotation_deg=0, translation=0)
POSE_ERROR_ALONE = dict(gain=0, white_balance=0, noise=0, vignetting=0)


def captured(folder: Path, capture: CaptureModel | None) -> Dataset:
    """The demo scene's first 2 frames at `folder` through `capture` (written unless there)."""
    if not (folder / "poses_bounds.npy").exists():
        write_n3v(folder, SyntheticScene(seed=0, duration=1.0), num_frames=2, capture=capture)
    return load_n3v(folder, prefer_png=True)


def dome(folder: Path, model: str) -> Dataset:
    """The scene's outward-facing dome of 12 `model` cameras (stg_train.synthetic.write_immersive), 2 frames."""
    if not (folder / "models.json").exists():
        write_immersive(folder, SyntheticScene(seed=0, duration=1.0), num_frames=2, model=model)
    return load_dataset(folder)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", help="folder for the captures (default: a new temporary one)")
    ap.add_argument("--json", help="also write the rows here")
    args = ap.parse_args()
    root = Path(args.data or tempfile.mkdtemp(prefix="stg_rig_calibration_"))
    clean = captured(root / "clean", None)
    captures = {"clean": clean,
                "realistic, seed 0": captured(root / "realistic-0", CaptureModel(seed=0)),
                "realistic, seed 1": captured(root / "realistic-1", CaptureModel(seed=1)),
                "pose error alone": captured(root / "pose", CaptureModel(seed=0, **POSE_ERROR_ALONE)),
                "vignetting alone": captured(root / "vignetting", CaptureModel(seed=0, **VIGNETTING_ALONE)),
                "clean, every other lens 30 %": with_vignetting(clean, [c for c in clean.train_cameras if c % 2]),
                "clean, one lens 30 %": with_vignetting(clean, [clean.train_cameras[2]]),
                "dome of fisheyes, clean": dome(root / "dome-fisheye", "fisheye"),
                "dome of pinholes, clean": dome(root / "dome-pinhole", "pinhole")}
    rows = []
    for name, dataset in captures.items():
        start = time.perf_counter()
        config, calibration = calibrate_rig(dataset, TrainConfig())
        seconds, e = time.perf_counter() - start, calibration.estimate
        rows.append({"capture": name, "corner": e.corner_brightness, "camera_corners": e.camera_corners.tolist(),
                     "gain_spread": e.gain_spread, "epipolar": e.epipolar, "seconds": seconds,
                     "lens_falloff": config.lens_falloff, "appearance": config.appearance,
                     "pose_refine": config.pose_refine})
        k = config.lens_falloff
        falloff = "none" if k is None else f"K1 {k[0]:.3f}, K2 {k[1]:.3f}"
        print(f"{name:30s} corner {e.corner_brightness:.3f}  cameras {e.camera_corners.min():.3f}-"
              f"{e.camera_corners.max():.3f}  gains {100 * e.gain_spread:4.1f} %  epipolar {e.epipolar:.3f} px  "
              f"({seconds:.1f} s)  -> falloff {falloff}, appearance {'on' if config.appearance else 'off'}, "
              f"poses {'refined' if config.pose_refine else 'kept'}", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
