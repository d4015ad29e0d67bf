#!/usr/bin/env python
"""Ablation of the paper's Table 4 on the default synthetic scene: the full model, then each component
switched off, trained with the same settings and seed; prints held-out PSNR (whole image, and apart for
the dynamic and the static pixels), DSSIM1, Gaussians and training time per variant beside the full
model, and the same dynamic / static PSNR at two novel views inside the rig (ground truth ray traced).

    python bench/ablation.py [--iterations N] [--points N] [--cameras C] [--frames F] [--width W]
                             [--height H] [--variants full,no-motion,...] [--set KEY=VALUE ...]
                             [--no-novel] [--threads 2] [--json PATH]

Variants (TrainConfig settings): full; no-temporal-opacity (frozen temporal_opacity: opacity(t) = 1);
no-motion (frozen motion = 0); no-rotation (frozen omega = 0); no-feature-splatting (the lite model:
splatted base rgb, no view / time features, no decoder); no-guided (guided=False). --set changes a
TrainConfig field for every variant (VALUE is JSON, else a string: --set splatter=numba,
--set 'schedule={"densify_until": 600}'), which makes this the screening tool of docs/dynamic.md.
Defaults are the demo's (stg_train.pipeline DEMO_SCENE / DEMO_TRAINING: 12 cameras x 30 frames at
160x120, 1500 iterations, 8000 initial points), about 15-20 min per variant on 2 idle CPU cores;
`--iterations 500 --points 4000` took 11-16 min per variant on 2 cores shared with other jobs. Held-out
figures use the trainer's renderer on the held-out camera at every frame against the lossless PNG
frames (PSNR in dB; DSSIM1 = (1 - SSIM) / 2, scikit-image SSIM, data_range 1; dynamic pixels:
stg_train.metrics.dynamic_mask at its default threshold, per camera over the clip). Guided sampling only
acts on views whose SSIM is below 0.91 at its start: with a sparse initialisation (e.g. `--points 300
--variants full,no-guided`) it matters, with a dense one it may not.
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
from stg_train.metrics import evaluate_images
from stg_train.synthetic import SyntheticScene, novel_view_dataset
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


FIGURES = ("psnr", "dssim1", "dynamic_psnr", "static_psnr", "dynamic_ssim", "static_ssim", "dynamic_fraction")


def evaluate(trainer: Trainer, dataset) -> dict:
    """FIGURES: means over the test cameras of `dataset` at every frame (trainer's renderer, time
    j / num_frames as in training), dynamic and static regions per camera (metrics.evaluate_images)."""
    r = evaluate_images(lambda ci, j: trainer.render_numpy(dataset.cameras[ci], j / dataset.num_frames), dataset)
    return {k: r[k] for k in FIGURES}


def parse_setting(text: str) -> tuple[str, object]:
    """KEY=VALUE with VALUE as JSON when it parses, else the string."""
    key, sep, value = text.partition("=")
    if not sep:
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE, got {text!r}")
    try:
        return key, json.loads(value)
    except json.JSONDecodeError:
        return key, value


def _fmt(x, spec=".2f") -> str:
    return "-" if x is None else format(x, spec)


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
    ap.add_argument("--set", type=parse_setting, action="append", default=[], metavar="KEY=VALUE",
                    help="a TrainConfig field for every variant (VALUE as JSON, else a string)")
    ap.add_argument("--no-novel", action="store_true", help="skip the two novel views inside the rig")
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
    settings = dict(args.set)
    novel = None if args.no_novel else novel_view_dataset(SyntheticScene(seed=0, duration=args.frames / ds.fps),
                                                          args.frames, ds.fps, args.width, args.height)
    print(f"{ds}; {args.iterations} iterations, {args.points} initial points, seed {args.seed}, "
          f"{args.threads} threads, settings {settings}", flush=True)

    results = {}
    for name in names:
        label, overrides = VARIANTS[name]
        cfg = TrainConfig(**{**DEMO_TRAINING, "iterations": args.iterations, "num_points": args.points,
                             "seed": args.seed, **settings, **overrides})
        trainer = Trainer(ds, cfg)
        trainer.train(progress=False)
        guided = next((s for s in trainer.strategies if hasattr(s, "chosen")), None)
        added = sum(e["added"] for e in guided.log) if guided is not None else 0
        results[name] = {"label": label, **evaluate(trainer, ds),
                         "novel": None if novel is None else evaluate(trainer, novel), "gaussians": trainer.params.count,
                         "train_seconds": trainer.seconds, "guided_added": added,
                         "guided_log": [] if guided is None else guided.log,
                         "guided_view_ssim": [] if guided is None else guided.scores}
        r = results[name]
        novel_text = "" if novel is None else (f"  novel dynamic / static {_fmt(r['novel']['dynamic_psnr'])} / "
                                               f"{_fmt(r['novel']['static_psnr'])} dB")
        print(f"  {label:<34} {r['psnr']:6.2f} dB  dynamic / static {_fmt(r['dynamic_psnr'])} / "
              f"{_fmt(r['static_psnr'])} dB{novel_text}  DSSIM1 {r['dssim1']:.4f}  {r['gaussians']:6d} Gaussians  "
              f"{r['train_seconds']:6.0f} s  (guided added {added})", flush=True)
        if guided is not None and guided.scores:
            print(f"    training-view SSIM at guided_start {trainer.schedule.guided_start}: lowest "
                  f"{guided.scores[0][0]:.3f}, highest {guided.scores[-1][0]:.3f}; sampling: {guided.log}", flush=True)

    full = results.get("full")
    header = (f"| {'Method':<34} | PSNR (dB) | vs full | dynamic | vs full | static | novel dynamic | novel static "
              f"| DSSIM1 | Gaussians | train s | guided added |")
    lines = [header, "|" + "|".join("-" * (len(c)) for c in header.split("|")[1:-1]) + "|"]
    for name, r in results.items():
        def delta(key):
            if full is None or name == "full" or r[key] is None or full[key] is None:
                return ""
            return f"{r[key] - full[key]:+.2f}"
        nv = r["novel"] or {}
        lines.append(f"| {r['label']:<34} | {r['psnr']:9.2f} | {delta('psnr'):>7} | {_fmt(r['dynamic_psnr']):>7} | "
                     f"{delta('dynamic_psnr'):>7} | {_fmt(r['static_psnr']):>6} | {_fmt(nv.get('dynamic_psnr')):>13} | "
                     f"{_fmt(nv.get('static_psnr')):>12} | {r['dssim1']:.4f} | {r['gaussians']:9d} | "
                     f"{r['train_seconds']:7.0f} | {r['guided_added']:12d} |")
    print("\n".join(lines))
    if args.json:
        Path(args.json).write_text(json.dumps({"settings": {**vars(args), "set": settings}, "results": results}, indent=1) + "\n")


if __name__ == "__main__":
    main()
