#!/usr/bin/env python
"""A fisheye rig against a pinhole rig of the same coverage, on the synthetic scene: held-out and
novel-view PSNR, Gaussian count and file size (docs/datasets.md, "Fisheye cameras").

    python bench/fisheye.py [--hfov 120] [--iterations 3000] [--cameras 12] [--frames 30] [--size 160x120]
                            [--variants fisheye,pinhole] [--data DIR] [--out DIR] [--threads 2]

The scene (stg_train.synthetic) is rendered by the outward-facing dome rig of SyntheticScene.dome_cameras
twice, as `stg-synth --fisheye HFOV` and `stg-synth --pinhole-dome HFOV` write it: equidistant fisheye
cameras of horizontal field of view HFOV, and pinhole cameras of the same HFOV at the same poses, both
in the Immersive layout (camera_0001, the centre camera, held out). Each variant trains with
stg_train.pipeline.train (default settings, --iterations steps) into OUT/<variant>/ and is evaluated
with the runtime Player: on its held-out camera (every frame; a fisheye for the fisheye rig) and on the
pinhole novel views between the dome's cameras (SyntheticScene.dome_novel_cameras, ray traced, every 3rd
frame), the same views for both. Figures go to OUT/<variant>/bench.json and a table is printed.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import stg_train  # noqa: F401  (first: it configures OpenMP before torch loads)
import numpy as np

from stg_train.data import load_dataset
from stg_train.pipeline import train
from stg_train.synthetic import SyntheticScene, write_immersive
from stg_train.trainer import TrainConfig

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from init_layouts import novel_psnr  # noqa: E402  (the same evaluation of novel views)


def write_rigs(data: Path, scene: SyntheticScene, variants, cameras: int, frames: int, fps: float,
               size: tuple[int, int], hfov: float) -> None:
    """DIR/<variant> for each variant ("fisheye" or "pinhole"), written once (reused when present)."""
    for variant in variants:
        folder = data / variant
        if not (folder / "models.json").is_file():
            write_immersive(folder, scene, num_cameras=cameras, num_frames=frames, fps=fps, width=size[0],
                            height=size[1], hfov_deg=hfov, model=variant)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--variants", default="fisheye,pinhole")
    ap.add_argument("--hfov", type=float, default=120.0, help="horizontal field of view of both rigs (degrees)")
    ap.add_argument("--iterations", type=int, default=3000)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--cameras", type=int, default=12)
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--fps", type=float, default=30.0)
    ap.add_argument("--size", default="160x120")
    ap.add_argument("--data", default=os.path.join("/tmp", "stg-fisheye"))
    ap.add_argument("--out", default=os.path.join("/tmp", "stg-fisheye", "runs"))
    args = ap.parse_args()
    import torch

    torch.set_num_threads(args.threads)
    size = tuple(int(v) for v in args.size.lower().split("x"))
    variants = args.variants.split(",")
    data, out = Path(args.data), Path(args.out)
    scene = SyntheticScene(seed=0, duration=args.frames / args.fps)
    write_rigs(data, scene, variants, args.cameras, args.frames, args.fps, size, args.hfov)
    novel = scene.dome_novel_cameras(*size)
    rows = []
    for variant in variants:
        dataset = load_dataset(data / variant, show_progress=False)
        config = TrainConfig(iterations=args.iterations)
        print(f"== {variant}: {dataset}; {config.iterations} steps", flush=True)
        metrics = train(dataset, out / variant, config, quiet=True, lpips={})
        views = novel_psnr(out / variant / "model.stg", scene, {c.name: c for c in novel}, args.frames, args.fps)
        row = {"variant": variant, "hfov": args.hfov, "heldout_psnr": metrics["heldout"]["psnr"],
               "novel_psnr": views, "novel_mean": float(np.mean(list(views.values()))),
               "gaussians": metrics["gaussians"], "file_bytes": metrics["file_bytes"],
               "train_seconds": metrics["train_seconds"], "init": metrics.get("init")}
        (out / variant / "bench.json").write_text(json.dumps(row, indent=1) + "\n")
        rows.append(row)
        print(json.dumps(row), flush=True)
    names = [c.name for c in novel]
    print(f"\n{'rig':<10} {'held-out':>9} " + " ".join(f"{n:>8}" for n in names)
          + f" {'novel':>8} {'Gaussians':>9} {'MB':>6}")
    for r in rows:
        print(f"{r['variant']:<10} {r['heldout_psnr']:9.2f} " + " ".join(f"{r['novel_psnr'][n]:8.2f}" for n in names)
              + f" {r['novel_mean']:8.2f} {r['gaussians']:9d} {r['file_bytes'] / 1e6:6.2f}")
    print(f"(dB; held-out: camera_0001, every frame; novel: pinhole views between the cameras, every 3rd frame; "
          f"{args.iterations} steps, HFOV {args.hfov:g} degrees)", file=sys.stderr)


if __name__ == "__main__":
    main()
