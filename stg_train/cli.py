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
  stg-train scenes/long --out runs/long --segments 0-2    first three 50-frame segments (others elsewhere)

DATA is a dataset folder in one of these layouts (detected, or forced with --layout):
  n3v          Neural 3D Video: camXX.mp4 per camera + poses_bounds.npy (LLFF), optionally
               frames/camXX/*.png (lossless frames, read instead of the videos); cam00 held out
  technicolor  <Scene>_undist_<frame>_<cam>.png + cameras_parameters.txt; cam10 held out
  reference    the reference code's preprocessed colmap_<i>/images/camXX.png + colmap_<i>/sparse/0
               (one folder per frame); cam00 held out
  rig          your own capture: images/<camera>/<frame>.png (or videos/<camera>.mp4) + one COLMAP
               model of the rig in sparse/0 (one image per camera); the first camera (by name) held out
--test-camera NAME holds out another camera; --fps sets the frame rate of layouts without one (default 30).
Writes OUT/model.stg (the player's file), OUT/checkpoint.pt and OUT/metrics.json. A video longer than
--segment-frames is trained as consecutive independent segments, each in OUT/segments/NN/ (checkpoint.pt,
model.stg, metrics.json), merged into one OUT/model.stg once every segment is trained.
Exit codes: 0 done, 2 bad data or arguments."""

EVAL_EPILOG = """Renders the held-out camera(s) of DATA (cam00 for N3V; --test-camera to choose) at every frame through the runtime player
and compares with the ground truth: PSNR (dB), SSIM (scikit-image, data_range 1), DSSIM1 = (1 - SSIM)/2
with data_range 1 and DSSIM2 with data_range 2 (the paper's Sec. 6.1), render FPS, model size."""

DEMO_DEFAULTS = {"cameras": 12, "frames": 30, "fps": 30.0, "width": 160, "height": 120}
#: Training settings of the demo (30 dB held-out after ~500 steps, ~6 min; the run ~15-20 min on 2 CPU cores).
DEMO_TRAINING = {"iterations": 1500, "num_points": 8000}


def ensure_demo_scene(data, announce: bool = False, **sizes) -> Path:
    """The demo's synthetic scene, in the N3V layout, at `data`: written unless it is there already.
    sizes: any of DEMO_DEFAULTS' cameras, frames, width, height to change; announce: say so on stderr
    before writing."""
    from .synthetic import SyntheticScene, write_n3v

    d = {**DEMO_DEFAULTS, **sizes}
    data = Path(data)
    if not (data / "poses_bounds.npy").exists():
        if announce:
            print(f"writing the synthetic scene ({d['cameras']} cameras x {d['frames']} frames, "
                  f"{d['width']}x{d['height']}) to {data}", file=sys.stderr)
        write_n3v(data, SyntheticScene(seed=0, duration=d["frames"] / d["fps"]), num_cameras=d["cameras"],
                  num_frames=d["frames"], fps=d["fps"], width=d["width"], height=d["height"])
    return data


def _positive_int(text: str) -> int:
    value = int(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text!r}")
    return value


def _segment_list(text: str) -> list[int]:
    from .segments import parse_segment_list

    try:
        return parse_segment_list(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


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
    p.add_argument("data", nargs="?", metavar="DATA", help="dataset folder (see below); omit with --demo")
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
    p.add_argument("--segment-frames", type=_positive_int, default=50, metavar="N",
                   help="frames per segment: a longer video is trained as consecutive independent models of N "
                        "frames (a last piece under N/2 frames joins the segment before it), one folder "
                        "OUT/segments/NN each, merged into OUT/model.stg (default %(default)s, as the paper)")
    p.add_argument("--segments", type=_segment_list, default=None, metavar="LIST",
                   help="train only these segments, indices from 0: e.g. 2,3 or 0-2 (default: all); run "
                        "the others elsewhere, copy their OUT/segments/NN folders into OUT/segments, and "
                        "--resume (or stg-convert merge) writes OUT/model.stg; with --resume, finished "
                        "segments are kept and an unfinished one continues from its checkpoint")
    p.add_argument("--checkpoint-every", type=_positive_int, default=d.checkpoint_every, metavar="N",
                   help="write OUT/checkpoint.pt (atomically) every N steps and at the end (default %(default)s)")
    p.add_argument("--batch", type=_positive_int, default=d.batch, metavar="B",
                   help="training views per step, all at one random time (default %(default)s)")
    p.add_argument("--points", type=_positive_int, default=d.num_points, metavar="N",
                   help="initial Gaussians: the most SfM points kept (a random subset beyond), or the number "
                        "sampled in the cameras' common view volume (default %(default)s)")
    p.add_argument("--init", choices=["sfm", "volume"], default=None,
                   help="initial points: sfm = SIFT features matched and triangulated with the known poses "
                        "(pycolmap, CPU) on every --init-every'th frame, cached in DATA/.stg_cache/sfm, falling "
                        "back to volume with a warning when it finds too few points; volume = sampled in the "
                        "cameras' common view volume at photo-consistent depths, needs the layout's near/far "
                        "bounds (default: volume where the layout has near/far bounds, as N3V and the demo, "
                        "else sfm)")
    p.add_argument("--init-every", type=_positive_int, default=1, metavar="N",
                   help="run SfM on every N-th frame (default %(default)s: every frame, as the paper)")
    p.add_argument("--seed", type=int, default=d.seed, help="random seed (default %(default)s)")
    p.add_argument("--downscale", type=_positive_int, default=1, metavar="K",
                   help="divide the frames' width and height by K (default 1)")
    _add_layout_options(p)
    p.add_argument("--from-video", action="store_true",
                   help="decode camXX.mp4 even when lossless frames/camXX/*.png exist")
    p.add_argument("--threads", type=_positive_int, default=None, metavar="N",
                   help="CPU threads for torch (default: torch's choice)")
    p.add_argument("--no-check", action="store_true",
                   help="skip comparing the runtime's render of the exported file with the trainer's")
    p.add_argument("--no-guided", action="store_true",
                   help="no guided sampling (new Gaussians along the rays of high-error patches, the paper's "
                        "Sec. 4.4; on by default)")
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


def _add_layout_options(p: argparse.ArgumentParser) -> None:
    from .data import LAYOUTS

    p.add_argument("--layout", choices=("auto",) + LAYOUTS, default="auto",
                   help="dataset layout of DATA (default auto: detected from its files)")
    p.add_argument("--fps", type=float, default=None, metavar="FPS",
                   help="frame rate of the data (default: the videos', else 30 for layouts that store none)")
    p.add_argument("--test-camera", default=None, metavar="NAME",
                   help="camera held out for evaluation (default: cam00 for n3v and reference, cam10 for "
                        "technicolor, the first camera by name for rig)")


def load_dataset(path, downscale: int = 1, from_video: bool = False, quiet: bool = False, layout: str = "auto",
                 fps: float | None = None, test_camera: str | None = None):
    """stg_train.data.load_dataset with a progress bar while the frame cache is built."""
    from stg_runtime.progress import progress_callback

    from .data import load_dataset as load

    with progress_callback("decode frames", enabled=not quiet) as report:
        return load(path, layout, downscale, from_video=from_video, fps=fps, test_camera=test_camera,
                    progress=report)


def default_init(dataset) -> str:
    """The --init default: "volume" when the dataset has near/far depth bounds (N3V, the demo), else "sfm".

    On the demo scene (160x120) the view-volume points trained to 28.1 dB held-out after 300 of 1500
    steps, the SfM points to 25.7 dB (SIFT finds ~500 points per frame at that size); layouts without
    bounds can only use SfM."""
    return "volume" if dataset.bounds is not None else "sfm"


def _new_trainer(dataset, config, out: Path, quiet: bool = False):
    """Trainer(dataset, config, out) with a progress bar while SfM computes the initial points; its
    warnings (SfM found too few points) are printed as "stg-train: warning: ..." lines."""
    import warnings

    from stg_runtime.progress import progress_callback

    from .trainer import Trainer

    with progress_callback("structure from motion", enabled=not quiet) as report:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            trainer = Trainer(dataset, config, out_dir=out, init_progress=report)
    for w in caught:
        print(f"stg-train: warning: {w.message}", file=sys.stderr)
    return trainer


def run_training(dataset, out: Path, config, resume: bool = False, quiet: bool = False, check: bool = True,
                 segment_frames: int | None = None, segments=None) -> dict:
    """Train (or resume) into `out`, export out/model.stg, evaluate it with the runtime and write
    out/metrics.json; returns the metrics. With segment_frames, a video of more frames (or any run
    naming `segments`, a list of indices) is trained segment by segment (stg_train.segments)."""
    from stg_runtime.player import Player

    from .segments import plan_segments, train_segments

    if segment_frames and (segments is not None or len(plan_segments(dataset.num_frames, segment_frames)) > 1):
        return train_segments(dataset, out, config, segment_frames, segments, resume, quiet, check)

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
        trainer = _new_trainer(dataset, config, out, quiet)
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
    from .segments import SegmentError
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
    config.guided = not args.no_guided
    config.init_every = args.init_every
    try:
        dataset = load_dataset(args.data, args.downscale, args.from_video, args.quiet, layout=args.layout,
                               fps=args.fps, test_camera=args.test_camera)
        config.init = args.init or default_init(dataset)
        metrics = run_training(dataset, Path(args.out), config, args.resume, args.quiet, not args.no_check,
                               args.segment_frames, args.segments)
    except (DataError, SegmentError) as e:
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
    p.add_argument("data", metavar="DATA", help="the dataset folder it was trained on (any layout of stg-train)")
    p.add_argument("--json", metavar="PATH", help="also write the figures (and per-frame values) as JSON")
    p.add_argument("--downscale", type=_positive_int, default=1, metavar="K",
                   help="divide the frames' size by K, as in training (default 1)")
    _add_layout_options(p)
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
        dataset = load_dataset(args.data, args.downscale, args.from_video, args.quiet, layout=args.layout,
                               fps=args.fps, test_camera=args.test_camera)
    except DataError as e:
        return _error("stg-eval", str(e))
    first, end = player.model.start_frame, player.model.start_frame + player.num_frames
    if first >= dataset.num_frames or abs(player.fps - dataset.fps) > 1e-6:
        return _error("stg-eval", f"{args.model}: covers frames {first}-{end - 1} at {player.fps:g} fps, the "
                      f"dataset has {dataset.num_frames} at {dataset.fps:g} fps")
    if first > 0 or end < dataset.num_frames:  # a model of some segments only (stg-train --segments)
        print(f"stg-eval: {args.model} covers frames {first}-{end - 1} of the dataset's {dataset.num_frames}: "
              "evaluating those", file=sys.stderr)
    result = evaluate_player(player, dataset, frames=range(first, min(end, dataset.num_frames)))
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

    from .trainer import TrainConfig

    args = build_train_parser().parse_args(argv)
    out = Path(args.out or "stg-demo")
    data = ensure_demo_scene(out / "data", announce=not args.quiet)
    import torch

    if args.threads:
        torch.set_num_threads(args.threads)
    config = TrainConfig(**DEMO_TRAINING)
    config.model, config.seed, config.checkpoint_every = args.model, args.seed, args.checkpoint_every
    config.guided = not args.no_guided
    config.init_every = args.init_every
    if args.iterations:
        config.iterations = args.iterations
    start = time.perf_counter()
    dataset = load_dataset(data, quiet=args.quiet)
    config.init = args.init or default_init(dataset)
    metrics = run_training(dataset, out, config, args.resume, args.quiet, not args.no_check,
                           args.segment_frames, args.segments)
    if metrics.get("missing_segments"):
        return 0  # OUT/model.stg waits for the other segments (train_segments said which)
    player = Player(out / "model.stg", device="cpu")
    train_cams = [dataset.cameras[i] for i in dataset.train_cameras]
    path = orbit(train_cams, dataset.num_frames)
    player.render_video(out / "orbit.mp4", path, times=np.arange(dataset.num_frames) / dataset.fps,
                        progress=not args.quiet)
    print(format_table(metrics["heldout"], metrics["file_bytes"], metrics["gaussians"]))
    print(f"demo done in {time.perf_counter() - start:.0f} s: {out / 'model.stg'}, {out / 'metrics.json'}, "
          f"{out / 'orbit.mp4'}")
    return 0
