#!/usr/bin/env python
"""Compression presets on a trained model of the default synthetic scene: file size, ratio to the
float32 file, Gaussians, held-out PSNR (runtime Player, cam00, every frame) and its change, the time
to compress and the time to read the file (stg_runtime.format.load, the best of 3).

    python bench/compress.py [--model MODEL.stg] [--data DIR] [--iterations N] [--out DIR] [--threads 2]

Without --model it generates the demo scene (12 cameras x 30 frames, 160x120) into --data and trains
the demo's full model for --iterations steps (the demo's settings otherwise). The float32 file is the
model written as the trainer writes it (float32, zlib level 6). Each preset runs twice: with the
dataset (the error budget from held-out views and the model's PSNR there) and without (the file's
cameras, model PSNR assumed 33 dB), as `stg-convert compress` with and without --data.

--finetune N (repeatable) adds rows of web with fine-tuning (stg_train.convert.finetune: N steps
against the training frames pruning --prune of the Gaussians, those that contribute least to the
training views, in --prune-stages stages, then web within what is left); --only-finetune skips the
presets, --preset P (repeatable) keeps only P's rows. --finetune-quantised M (repeatable) then
fine-tunes M more steps through fake quantisation below the bits web chose and searches again
(stg-convert compress --finetune-quantised M). --still D (repeatable) holds the Gaussians that move
less than D x the cameras' extent still while fine-tuning (stg-convert compress --still D).
"""
from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import stg_train  # noqa: F401  (first: it configures OpenMP before torch loads)
from stg_runtime import format as stg_format
from stg_runtime.player import Player
from stg_train.pipeline import DEMO_TRAINING, ensure_demo_scene
from stg_train.convert.compress import PRESETS, compress_file
from stg_train.data import load_n3v
from stg_train.metrics import evaluate_player


def train(ds, out: Path, iterations: int, threads: int) -> Path:
    import torch

    from stg_train.export import export_trainer
    from stg_train.trainer import Trainer, TrainConfig

    torch.set_num_threads(threads)
    cfg = TrainConfig(**{**DEMO_TRAINING, "iterations": iterations})
    trainer = Trainer(ds, cfg)
    trainer.train(progress=True)
    print(f"trained {iterations} steps in {trainer.seconds:.0f} s: {trainer.params.count} Gaussians", flush=True)
    return export_trainer(trainer, out / "model.stg", check=False).path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", help="a trained .stg model of --data (default: train one)")
    ap.add_argument("--data", default=os.path.join(tempfile.gettempdir(), "stg-bench-scene"))
    ap.add_argument("--iterations", type=int, default=600, help="training steps when training (default 600)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--finetune", type=int, action="append", default=[], metavar="N",
                    help="also web with N fine-tuning steps (repeatable)")
    ap.add_argument("--prune", type=float, action="append", default=[], metavar="F",
                    help="fractions pruned before fine-tuning (repeatable; default 0.5)")
    ap.add_argument("--finetune-quantised", type=int, action="append", default=[], metavar="M",
                    help="with --finetune: quantisation-aware steps after it (repeatable; default 0)")
    ap.add_argument("--prune-stages", type=int, action="append", default=[], metavar="K",
                    help="with --finetune: prune in K stages while fine-tuning (repeatable; default "
                         "stg_train.convert.finetune.PRUNE_STAGES)")
    ap.add_argument("--still", type=float, action="append", default=[], metavar="D",
                    help="with --finetune: hold Gaussians that move less than D x the extent still "
                         "(repeatable; default 0)")
    ap.add_argument("--preset", action="append", choices=list(PRESETS), default=[],
                    help="only this preset's rows (repeatable; default all)")
    ap.add_argument("--only-finetune", action="store_true", help="skip the presets' rows")
    ap.add_argument("--out", default=None, help="where the compressed files go (default: a temp folder)")
    args = ap.parse_args()
    ds = load_n3v(ensure_demo_scene(args.data), prefer_png=True)
    out = Path(args.out or tempfile.mkdtemp(prefix="stg-bench-compress-"))
    out.mkdir(parents=True, exist_ok=True)
    model_path = Path(args.model) if args.model else train(ds, out, args.iterations, args.threads)
    model = stg_format.load(model_path)
    f32 = len(stg_format.dumps(model))
    base = evaluate_player(Player(model, device="cpu"), ds)["psnr"]
    print(f"{model_path}: {model.kind} model, {sum(s.count for s in model.segments)} Gaussians, "
          f"float32 file {f32} bytes, held-out PSNR {base:.2f} dB ({ds})", flush=True)
    rows = [("float32 (trainer)", f32, sum(s.count for s in model.segments), base, 0.0, 0.0, load_seconds(model_path))]
    presets = args.preset or list(PRESETS)
    runs = [(preset, True) for preset in presets] + [(preset, False) for preset in presets if preset != "lossless"]
    runs = [] if args.only_finetune else runs
    if args.threads:
        import torch

        torch.set_num_threads(args.threads)
    for steps in args.finetune:
        for prune in args.prune or [0.5]:
            for quantised in args.finetune_quantised or [0]:
                for stages in args.prune_stages or [None]:
                    for still in args.still or [0.0]:
                        rows.append(finetune_row(model_path, ds, out, steps, prune, base, quantised, stages, still))
    for preset, with_data in runs:
        name = preset if with_data else f"{preset}, no --data"
        path = out / f"model.{preset}{'' if with_data else '.nodata'}.stg"
        start = time.perf_counter()
        report = compress_file(model_path, path, preset, dataset=ds if with_data else None)
        seconds = time.perf_counter() - start
        print(report.format(), flush=True)
        psnr = evaluate_player(Player(path, device="cpu"), ds)["psnr"]
        rows.append((name, report.file_after, report.gaussians_after, psnr, psnr - base, seconds, load_seconds(path)))
    print("\n| preset | file bytes | ratio to float32 | Gaussians | held-out PSNR | PSNR change | compress time | "
          "read time |")
    print("|---|---|---|---|---|---|---|---|")
    for name, size, count, psnr, change, seconds, load in rows:
        print(f"| {name} | {size:,} | {size / f32:.3f} (1/{f32 / size:.1f}) | {count:,} | {psnr:.2f} dB | "
              f"{change:+.3f} dB | {seconds:.0f} s | {1000 * load:.0f} ms |")


def finetune_row(model_path, ds, out: Path, steps: int, prune: float, base: float, quantised: int = 0,
                 stages: int | None = None, still: float = 0.0) -> tuple:
    """The table row of web after `steps` fine-tuning steps pruning `prune` in `stages` (default
    PRUNE_STAGES), holding still those that move less than `still` x the extent, and `quantised`
    quantisation-aware ones (finetune_file)."""
    from stg_train.convert.finetune import PRUNE_STAGES, finetune_file

    stages = PRUNE_STAGES if stages is None else stages
    path = out / f"model.web.ft{steps}.p{round(100 * prune)}.k{stages}.q{quantised}.s{round(100 * still)}.stg"
    start = time.perf_counter()
    report, info = finetune_file(model_path, path, ds, steps, "web", prune, quantised_steps=quantised,
                                 stages=stages, still=still)
    seconds = time.perf_counter() - start
    print(report.format(), flush=True)
    print(info.format(), flush=True)
    psnr = evaluate_player(Player(path, device="cpu"), ds)["psnr"]
    name = (f"web, prune {prune:g} in {stages} + fine-tune {steps}"
            + (f" + quantised {quantised}" if quantised else "") + (f", still {still:g}" if still else ""))
    return (name, report.file_after, report.gaussians_after, psnr, psnr - base,
            seconds, load_seconds(path))


def load_seconds(path) -> float:
    """The best of 3 times to read `path` with stg_runtime.format.load (checksum, inflate, decode)."""
    times = []
    for _ in range(3):
        start = time.perf_counter()
        stg_format.load(path)
        times.append(time.perf_counter() - start)
    return min(times)


if __name__ == "__main__":
    main()
