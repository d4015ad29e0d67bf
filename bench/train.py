#!/usr/bin/env python
"""Training speed and quality on the default synthetic scene (12 cameras x 30 frames, 160x120) on this
machine: seconds per iteration, training time to reach 25 / 30 dB held-out PSNR, final PSNR (runtime
Player on the held-out camera, every frame), Gaussian count and file size.

    python bench/train.py [--iterations N] [--eval-every K] [--threads 2] [--model full|lite]
                          [--device cpu|cuda] [--splatter numba|torch|gsplat] [--data DIR] [--out DIR]

--splatter auto (the default) is what stg-train picks: numba on the CPU, gsplat on CUDA where
installed; `--splatter torch` times the reference torch splatter. On a GPU: `--device cuda` with the
torch splatter, or `--device cuda --splatter gsplat` with gsplat's kernels (the `[cuda]` extra).

Held-out PSNR is measured every K steps with the trainer's renderer over every frame of cam00; the time
that takes is excluded from the training time. The scene is generated once into --data.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import stg_train  # noqa: F401  (first: it configures OpenMP before torch loads)
import torch

from stg_train.pipeline import DEMO_TRAINING, ensure_demo_scene
from stg_train.data import load_n3v
from stg_train.export import export_trainer
from stg_train.metrics import evaluate_player
from stg_train.render import resolve_backend
from stg_train.trainer import Trainer, TrainConfig
from stg_runtime.player import Player

from machine import describe


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--iterations", type=int, default=DEMO_TRAINING["iterations"])
    ap.add_argument("--points", type=int, default=DEMO_TRAINING["num_points"])
    ap.add_argument("--eval-every", type=int, default=100)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--model", default="full", choices=["full", "lite"])
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--splatter", default="auto", choices=["auto", "numba", "torch", "gsplat"])
    ap.add_argument("--data", default=os.path.join(tempfile.gettempdir(), "stg-bench-scene"))
    ap.add_argument("--out", default=None, help="where model.stg and bench.json go (default: a temp folder)")
    args = ap.parse_args()
    if args.device == "cuda" and not torch.cuda.is_available():
        raise SystemExit(f"bench/train.py --device cuda: torch {torch.__version__} sees no CUDA GPU here")
    torch.set_num_threads(args.threads)
    ds = load_n3v(ensure_demo_scene(args.data), prefer_png=True)
    out = Path(args.out or tempfile.mkdtemp(prefix="stg-bench-"))
    cfg = TrainConfig(**{**DEMO_TRAINING, "iterations": args.iterations, "num_points": args.points,
                         "model": args.model, "device": args.device,
                         "splatter": resolve_backend(args.splatter, args.device)})
    print(f"{describe()}; torch {torch.__version__} ({torch.backends.cpu.get_cpu_capability()}), {args.threads} threads; "
          f"{ds}; {cfg.device}, {cfg.splatter} splatter; {cfg.model} model, {cfg.iterations} iterations, {cfg.num_points} initial points", flush=True)

    start = time.perf_counter()
    trainer = Trainer(ds, cfg)
    init_seconds = time.perf_counter() - start
    reached: dict[int, float | None] = {25: None, 30: None}
    curve = []

    def check(t: Trainer) -> None:
        if t.step % args.eval_every and t.step != cfg.iterations:
            return
        psnr = t.heldout_psnr()
        curve.append({"step": t.step, "seconds": round(t.seconds, 1), "psnr": round(psnr, 2),
                      "gaussians": t.params.count})
        for target in reached:
            if reached[target] is None and psnr >= target:
                reached[target] = t.seconds
        print(f"  step {t.step:5d}  {t.seconds:7.1f} s  held-out {psnr:6.2f} dB  {t.params.count} Gaussians",
              flush=True)

    cpu_start = time.process_time()
    trainer.train(progress=False, callback=check)
    cpu_seconds = time.process_time() - cpu_start
    report = export_trainer(trainer, out / "model.stg")
    final = evaluate_player(Player(report.path, device="cpu"), ds)
    fmt = lambda s: "not reached" if s is None else f"{s:.0f} s"  # noqa: E731
    rows = [("seconds per iteration", f"{trainer.seconds / trainer.step:.3f}"),
            ("initialisation", f"{init_seconds:.1f} s"),
            ("time to 25 dB held-out", fmt(reached[25])),
            ("time to 30 dB held-out", fmt(reached[30])),
            ("training time", f"{trainer.seconds:.0f} s"),
            ("CPU time of the training (all threads, evaluations included)", f"{cpu_seconds:.0f} s"),
            ("final held-out PSNR (Player)", f"{final['psnr']:.2f} dB"),
            ("final SSIM / DSSIM1", f"{final['ssim']:.4f} / {final['dssim1']:.4f}"),
            ("Gaussians", str(trainer.params.count)),
            ("file size", f"{report.bytes / 1e6:.2f} MB"),
            ("export check max |diff|", f"{report.diff.max_abs:.2e}"),
            ("render FPS (Player, CPU)", f"{final['fps']:.1f}")]
    width = max(len(k) for k, _ in rows)
    print("\n".join(f"{k:<{width}}  {v}" for k, v in rows))
    (out / "bench.json").write_text(json.dumps({"rows": dict(rows), "curve": curve}, indent=1))
    print(f"model and bench.json in {out}", file=sys.stderr)


if __name__ == "__main__":
    main()
