#!/usr/bin/env python
"""Ablation of the paper's Table 4 on the default synthetic scene: the full model, then each component
switched off, trained with the same settings and seed; prints held-out PSNR, DSSIM1, Gaussians and
training time per variant beside the full model.

    python bench/ablation.py [--iterations N] [--points N] [--cameras C] [--frames F] [--width W]
                             [--height H] [--variants full,no-motion,...] [--threads 2] [--json PATH]

Variants (TrainConfig settings): full; no-temporal-opacity (frozen temporal_opacity: opacity(t) = 1);
no-motion (frozen motion = 0); no-rotation (frozen omega = 0); no-feature-splatting (the lite model:
splatted base rgb, no view / time features, no decoder); no-guided (guided=False). Defaults are the
demo's (stg_train.pipeline DEMO_SCENE / DEMO_TRAINING: 12 cameras x 30 frames at 160x120, 1500 iterations,
8000 initial points), about 15-20 min per variant on 2 idle CPU cores; `--iterations 500 --points 4000`
took 11-16 min per variant on 2 cores shared with other jobs. Held-out figures use the trainer's renderer
on the held-out camera at every frame (PSNR in dB; DSSIM1 = (1 - SSIM) / 2, scikit-image SSIM,
data_range 1). Guided sampling only acts on views whose SSIM is below 0.91 at its start: with a sparse
initialisation (e.g. `--points 300 --variants full,no-guided`) it matters, with a dense one it may not.
"""
from __future__ import annotations

import argparse
import json
import os
import tempfile
from pathlib import Path

import stg_train  # noqa: F401  (first: it configures OpenMP before torch loads)
import numpy as np
import torch

from stg_train.pipeline import DEMO_SCENE, DEMO_TRAINING, ensure_demo_scene
from stg_train.data import load_n3v
from stg_train.metrics import image_metrics
from stg_train.trainer import Trainer, TrainConfig

#: name -> (table label, TrainConfig overrides)
VARIANTS = {
    "full": ("Ours full", {}),
    "no-temporal-opacity": ("w/o temporal opacity", {"frozen": ("temporal_opacity",)}),
    "no-motion": ("w/o polynomial motion", {"frozen": ("motion",)}),
    "no-rotation": ("w/o polynomial rotation", {"frozen": ("rotation",)}),
    "no-feature-splatting": ("w/o feature splatting (lite rgb)", {"model": "lite"}),
    "no-guided": ("w/o guided sampling", {"guided": False}),
}


def heldout(trainer: Trainer) -> dict:
    """Mean PSNR / DSSIM1 over the held-out cameras at every frame (trainer's renderer)."""
    ds = trainer.dataset
    rows = [image_metrics(trainer.render_numpy(ds.cameras[ci], j / ds.num_frames), ds.image(ci, j))
            for ci in ds.test_cameras for j in range(ds.num_frames)]
    return {k: float(np.mean([r[k] for r in rows])) for k in ("psnr", "dssim1")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    d = DEMO_SCENE
    ap.add_argument("--iterations", type=int, default=DEMO_TRAINING["iterations"])
    ap.add_argument("--points", type=int, default=DEMO_TRAINING["num_points"])
    ap.add_argument("--cameras", type=int, default=d["cameras"])
    ap.add_argument("--frames", type=int, default=d["frames"])
    ap.add_argument("--width", type=int, default=d["width"])
    ap.add_argument("--height", type=int, default=d["height"])
    ap.add_argument("--variants", default=",".join(VARIANTS), help="comma-separated subset of: " + ", ".join(VARIANTS))
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--data", default=None, help="scene folder (generated once; default: a temp folder per size)")
    ap.add_argument("--json", default=None, help="also write the table as JSON here")
    args = ap.parse_args()
    names = [n.strip() for n in args.variants.split(",") if n.strip()]
    unknown = [n for n in names if n not in VARIANTS]
    if unknown:
        ap.error(f"unknown variant(s) {unknown}; choose from {list(VARIANTS)}")
    torch.set_num_threads(args.threads)
    size = f"{args.cameras}x{args.frames}-{args.width}x{args.height}"
    data = Path(args.data or os.path.join(tempfile.gettempdir(), f"stg-ablation-scene-{size}"))
    ensure_demo_scene(data, cameras=args.cameras, frames=args.frames, width=args.width, height=args.height)
    ds = load_n3v(data, prefer_png=True)
    print(f"{ds}; {args.iterations} iterations, {args.points} initial points, seed {args.seed}, "
          f"{args.threads} threads", flush=True)

    results = {}
    for name in names:
        label, overrides = VARIANTS[name]
        cfg = TrainConfig(**{**DEMO_TRAINING, "iterations": args.iterations, "num_points": args.points,
                             "seed": args.seed, **overrides})
        trainer = Trainer(ds, cfg)
        trainer.train(progress=False)
        guided = next((s for s in trainer.strategies if hasattr(s, "chosen")), None)
        added = sum(e["added"] for e in guided.log) if guided is not None else 0
        results[name] = {"label": label, **heldout(trainer), "gaussians": trainer.params.count,
                         "train_seconds": trainer.seconds, "guided_added": added,
                         "guided_log": [] if guided is None else guided.log,
                         "guided_view_ssim": [] if guided is None else guided.scores}
        r = results[name]
        print(f"  {label:<34} {r['psnr']:6.2f} dB  DSSIM1 {r['dssim1']:.4f}  {r['gaussians']:6d} Gaussians  "
              f"{r['train_seconds']:6.0f} s  (guided added {added})", flush=True)
        if guided is not None and guided.scores:
            print(f"    training-view SSIM at guided_start {trainer.schedule.guided_start}: lowest "
                  f"{guided.scores[0][0]:.3f}, highest {guided.scores[-1][0]:.3f}; sampling: {guided.log}", flush=True)

    full = results.get("full")
    header = f"| {'Method':<34} | PSNR (dB) | vs full | DSSIM1 | Gaussians | train s | guided added |"
    lines = [header, "|" + "|".join("-" * (len(c)) for c in header.split("|")[1:-1]) + "|"]
    for name, r in results.items():
        delta = "" if full is None or name == "full" else f"{r['psnr'] - full['psnr']:+.2f}"
        lines.append(f"| {r['label']:<34} | {r['psnr']:9.2f} | {delta:>7} | {r['dssim1']:.4f} | {r['gaussians']:9d} | "
                     f"{r['train_seconds']:7.0f} | {r['guided_added']:12d} |")
    print("\n".join(lines))
    if args.json:
        Path(args.json).write_text(json.dumps({"settings": vars(args), "results": results}, indent=1) + "\n")


if __name__ == "__main__":
    main()
