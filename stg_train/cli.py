"""Command lines: `stg-train` (train, or `--demo`), `stg-eval` (evaluate a model on a dataset)."""
from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import asdict
from pathlib import Path

TRAIN_EPILOG = """examples:
  stg-train --demo --out demo/                  synthetic scene -> train on the CPU -> model, metrics, video
  stg-train scenes/coffee --out runs/coffee --iterations 30000 --device cuda
  stg-train scenes/coffee --out runs/coffee --resume      continue from runs/coffee/checkpoint.pt

DATA is a Neural 3D Video folder: camXX.mp4 per camera + poses_bounds.npy (LLFF), optionally
frames/camXX/*.png (lossless frames, read instead of the videos). cam00 is held out for evaluation.
Writes OUT/model.stg (the player's file), OUT/checkpoint.pt and OUT/metrics.json.
Exit codes: 0 done, 2 bad data or arguments."""

EVAL_EPILOG = """Renders the held-out camera(s) of DATA (cam00 for N3V) at every frame through the runtime player
and compares with the ground truth: PSNR (dB), SSIM (scikit-image, data_range 1), DSSIM1 = (1 - SSIM)/2
with data_range 1 and DSSIM2 with data_range 2 (the paper's Sec. 6.1), render FPS, model size."""

DEMO_DEFAULTS = {"cameras": 12, "frames": 30, "fps": 30.0, "width": 160, "height": 120}
#: Training settings of the demo (30 dB held-out after ~500 steps, ~6 min; the run ~15-20 min on 2 CPU cores).
DEMO_TRAINING = {"iterations": 1500, "num_points": 8000}


def _positive_int(text: str) -> int:
    value = int(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text!r}")
    return value


def _error(prog: str, message: str) -> int:
    print(f"{prog}: error: {message}", file=sys.stderr)
    return 2


# -- stg-train ------------------------------------------------------------------------------------
def build_train_parser() -> argparse.ArgumentParser:
    from .trainer import TrainConfig

    d = TrainConfig()
    p = argparse.ArgumentParser(
        prog="stg-train", epilog=TRAIN_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Learn Spacetime Gaussians from synchronised multi-view video and write a .stg model.")
    p.add_argument("data", nargs="?", metavar="DATA", help="dataset folder (N3V layout); omit with --demo")
    p.add_argument("--out", metavar="DIR", help="output folder (created if missing); required unless --demo "
                   "(default for --demo: stg-demo)")
    p.add_argument("--model", choices=["full", "lite"], default=d.model,
                   help="full: 9 features per Gaussian + colour decoder MLP (view- and time-dependent "
                        "colour); lite: plain rgb, smaller and faster (default %(default)s)")
    p.add_argument("--iterations", type=_positive_int, default=None, metavar="N",
                   help=f"optimisation steps; the density-control schedule is stretched to N (default {d.iterations}, "
                        "the demo's own default with --demo)")
    p.add_argument("--splatter", choices=["auto", "torch", "gsplat"], default="auto",
                   help="rasteriser: torch = the built-in differentiable splatter (CPU and CUDA); gsplat = the "
                        "gsplat library's CUDA kernels (pip install -e \".[cuda]\"; needs --device cuda); "
                        "auto = gsplat when it can run, else torch (default auto)")
    p.add_argument("--device", choices=["cpu", "cuda"], default="cpu",
                   help="where the parameters live and rendering runs (default cpu)")
    p.add_argument("--resume", action="store_true",
                   help="continue from OUT/checkpoint.pt with its settings (a killed run resumed this way "
                        "reaches the same state as an uninterrupted one); starts afresh if there is none")
    p.add_argument("--checkpoint-every", type=_positive_int, default=d.checkpoint_every, metavar="N",
                   help="write OUT/checkpoint.pt (atomically) every N steps and at the end (default %(default)s)")
    p.add_argument("--batch", type=_positive_int, default=d.batch, metavar="B",
                   help="training views per step, all at one random time (default %(default)s)")
    p.add_argument("--points", type=_positive_int, default=d.num_points, metavar="N",
                   help="initial Gaussians, sampled in the cameras' common view volume (default %(default)s)")
    p.add_argument("--seed", type=int, default=d.seed, help="random seed (default %(default)s)")
    p.add_argument("--downscale", type=_positive_int, default=1, metavar="K",
                   help="divide the frames' width and height by K (default 1)")
    p.add_argument("--from-video", action="store_true",
                   help="decode camXX.mp4 even when lossless frames/camXX/*.png exist")
    p.add_argument("--threads", type=_positive_int, default=None, metavar="N",
                   help="CPU threads for torch (default: torch's choice)")
    p.add_argument("--no-check", action="store_true",
                   help="skip comparing the runtime's render of the exported file with the trainer's")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--demo", action="store_true",
                   help="generate the synthetic scene (12 cameras x 30 frames, 160x120) into OUT/data, train "
                        "on it, evaluate, and write OUT/model.stg, OUT/metrics.json and a novel-view video "
                        "OUT/orbit.mp4")
    return p


def resolve_splatter(name: str, device: str) -> str:
    """The backend to train with, "torch" or "gsplat": `auto` picks gsplat when it can run on `device`
    (installed, CUDA device present), else torch. Raises ValueError with the reason when `gsplat` is asked
    for explicitly and cannot run."""
    from .splat_gsplat import unavailable_reason

    if name == "torch":
        return "torch"
    reason = unavailable_reason(device)
    if name == "auto":
        return "torch" if reason else "gsplat"
    if reason:
        raise ValueError(f"--splatter gsplat: {reason}; use --splatter torch or auto")
    return "gsplat"


def load_dataset(path, downscale: int = 1, from_video: bool = False, quiet: bool = False):
    """load_n3v with a progress bar while the frame cache is built."""
    from stg_runtime.progress import Progress

    from .data import load_n3v

    bar = None

    def report(done: int, total: int) -> None:
        nonlocal bar
        if bar is None:
            bar = Progress(total=total, desc="decode frames", enabled=not quiet)
        bar.update(done - bar.count)

    try:
        return load_n3v(path, downscale=downscale, prefer_png=not from_video, progress=report)
    finally:
        if bar is not None:
            bar.close()


def run_training(dataset, out: Path, config, resume: bool = False, quiet: bool = False, check: bool = True) -> dict:
    """Train (or resume) into `out`, export out/model.stg, evaluate it with the runtime and write
    out/metrics.json; returns the metrics."""
    from stg_runtime.player import Player

    from .export import export_trainer
    from .metrics import evaluate_player
    from .trainer import Trainer

    out.mkdir(parents=True, exist_ok=True)
    ckpt = out / "checkpoint.pt"
    if resume and ckpt.exists():
        trainer = Trainer.resume(dataset, ckpt, out_dir=out, device=config.device, splatter=config.splatter)
        if not quiet:
            print(f"resuming {ckpt} at step {trainer.step} of {trainer.config.iterations}", file=sys.stderr)
    else:
        if resume and not quiet:
            print(f"no checkpoint in {out}: starting a new run", file=sys.stderr)
        trainer = Trainer(dataset, config, out_dir=out)
    trainer.train(progress=not quiet)
    report = export_trainer(trainer, out / "model.stg", check=check)
    result = evaluate_player(Player(report.path, device="cpu"), dataset)
    metrics = {"heldout": {k: result[k] for k in ("psnr", "ssim", "dssim1", "dssim2", "fps", "images", "cameras")},
               "iterations": trainer.step, "train_seconds": trainer.seconds, "gaussians": trainer.params.count,
               "file_bytes": report.bytes, "export_check": None if report.diff is None else report.diff._asdict(),
               "settings": asdict(trainer.config)}
    tmp = out / "metrics.json.tmp"
    tmp.write_text(json.dumps(metrics, indent=1) + "\n")
    tmp.replace(out / "metrics.json")
    return metrics


def train_main(argv=None) -> int:
    """Entry point of `stg-train`."""
    from .data import DataError
    from .trainer import TrainConfig

    parser = build_train_parser()
    args = parser.parse_args(argv)
    if args.demo:
        return demo_main(argv)
    if args.data is None:
        parser.error("give a DATA folder (or --demo)")
    if args.out is None:
        parser.error("--out DIR is required")
    try:
        splatter = resolve_splatter(args.splatter, args.device)
    except ValueError as e:
        return _error("stg-train", str(e))
    import torch

    if args.device == "cuda" and not torch.cuda.is_available():
        return _error("stg-train", "--device cuda: torch sees no CUDA device")
    if args.threads:
        torch.set_num_threads(args.threads)
    config = TrainConfig(model=args.model, batch=args.batch, num_points=args.points, seed=args.seed,
                         device=args.device, checkpoint_every=args.checkpoint_every, splatter=splatter)
    if args.iterations:
        config.iterations = args.iterations
    try:
        dataset = load_dataset(args.data, args.downscale, args.from_video, args.quiet)
        metrics = run_training(dataset, Path(args.out), config, args.resume, args.quiet, not args.no_check)
    except DataError as e:
        return _error("stg-train", str(e))
    print(format_table(metrics["heldout"], metrics["file_bytes"], metrics["gaussians"]))
    return 0


# -- stg-eval -------------------------------------------------------------------------------------
def format_table(figures: dict, file_bytes: int, gaussians: int | None = None) -> str:
    rows = [("PSNR (dB)", f"{figures['psnr']:.2f}"), ("SSIM", f"{figures['ssim']:.4f}"),
            ("DSSIM1", f"{figures['dssim1']:.4f}"), ("DSSIM2", f"{figures['dssim2']:.4f}"),
            ("render FPS", f"{figures['fps']:.1f}"), ("model size (MB)", f"{file_bytes / 1e6:.2f}")]
    if gaussians is not None:
        rows.append(("Gaussians", str(gaussians)))
    rows.append(("images", f"{figures['images']} ({', '.join(figures['cameras'])})"))
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"{k:<{width}}  {v}" for k, v in rows)


def build_eval_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="stg-eval", epilog=EVAL_EPILOG,
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                description="Evaluate a .stg model on a dataset's held-out camera.")
    p.add_argument("model", metavar="MODEL", help="the .stg file")
    p.add_argument("data", metavar="DATA", help="the dataset folder it was trained on (N3V layout)")
    p.add_argument("--json", metavar="PATH", help="also write the figures (and per-frame values) as JSON")
    p.add_argument("--downscale", type=_positive_int, default=1, metavar="K",
                   help="divide the frames' size by K, as in training (default 1)")
    p.add_argument("--from-video", action="store_true", help="decode camXX.mp4 even when PNG frames exist")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    return p


def eval_main(argv=None) -> int:
    """Entry point of `stg-eval`."""
    from stg_runtime.format import FormatError
    from stg_runtime.player import Player

    from .data import DataError
    from .metrics import evaluate_player

    args = build_eval_parser().parse_args(argv)
    try:
        player = Player(args.model, device="cpu")
    except (OSError, FormatError) as e:
        return _error("stg-eval", str(e) if isinstance(e, FormatError) else f"{args.model}: {e.strerror or e}")
    try:
        dataset = load_dataset(args.data, args.downscale, args.from_video, args.quiet)
    except DataError as e:
        return _error("stg-eval", str(e))
    if player.num_frames < dataset.num_frames or abs(player.fps - dataset.fps) > 1e-6:
        return _error("stg-eval", f"{args.model}: covers {player.num_frames} frames at {player.fps:g} fps, the "
                      f"dataset has {dataset.num_frames} at {dataset.fps:g} fps")
    result = evaluate_player(player, dataset)
    size = Path(args.model).stat().st_size
    count = sum(s.count for s in player.model.segments)
    print(format_table(result, size, count))
    summary = {k: result[k] for k in ("psnr", "ssim", "dssim1", "dssim2", "fps", "images", "cameras")}
    summary.update(model=str(args.model), data=str(args.data), file_bytes=size, gaussians=count)
    print(json.dumps(summary))
    if args.json:
        Path(args.json).write_text(json.dumps({**summary, "per_frame": result["per_frame"]}, indent=1) + "\n")
    return 0


# -- the demo -------------------------------------------------------------------------------------
def demo_main(argv=None) -> int:
    """`stg-train --demo [--out DIR] [--iterations N] ...`: the synthetic scene, trained on the CPU."""
    import numpy as np

    from stg_runtime.camera import orbit
    from stg_runtime.player import Player

    from .synthetic import SyntheticScene, write_n3v
    from .trainer import TrainConfig

    args = build_train_parser().parse_args(argv)
    out = Path(args.out or "stg-demo")
    data = out / "data"
    d = DEMO_DEFAULTS
    if not (data / "poses_bounds.npy").exists():
        if not args.quiet:
            print(f"writing the synthetic scene ({d['cameras']} cameras x {d['frames']} frames, "
                  f"{d['width']}x{d['height']}) to {data}", file=sys.stderr)
        write_n3v(data, SyntheticScene(seed=0, duration=d["frames"] / d["fps"]), num_cameras=d["cameras"],
                  num_frames=d["frames"], fps=d["fps"], width=d["width"], height=d["height"])
    import torch

    if args.threads:
        torch.set_num_threads(args.threads)
    config = TrainConfig(**DEMO_TRAINING)
    config.model, config.seed, config.checkpoint_every = args.model, args.seed, args.checkpoint_every
    if args.iterations:
        config.iterations = args.iterations
    start = time.perf_counter()
    dataset = load_dataset(data, quiet=args.quiet)
    metrics = run_training(dataset, out, config, args.resume, args.quiet, not args.no_check)
    player = Player(out / "model.stg", device="cpu")
    train_cams = [dataset.cameras[i] for i in dataset.train_cameras]
    path = orbit(train_cams, dataset.num_frames)
    player.render_video(out / "orbit.mp4", path, times=np.arange(dataset.num_frames) / dataset.fps,
                        progress=not args.quiet)
    print(format_table(metrics["heldout"], metrics["file_bytes"], metrics["gaussians"]))
    print(f"demo done in {time.perf_counter() - start:.0f} s: {out / 'model.stg'}, {out / 'metrics.json'}, "
          f"{out / 'orbit.mp4'}")
    return 0
