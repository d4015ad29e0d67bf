"""`stg-train`: learn Spacetime Gaussians from a dataset folder (or the built-in demo scene)."""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from stg_runtime.player import RenderError

from ..data import DataError, load_dataset
from ..distributed import DistributedError
from ..data.points import METHODS
from ..pipeline import DEMO_SCENE, DEMO_TRAINING, run_demo, train
from ..render import resolve_backend
from ..threads import set_cpu_threads
from ..segments import SegmentError, parse_segment_list
from ..trainer import MOTION_INITS, TrainConfig
from .common import add_dataset_options, check_dataset_options, dataset_options, error, format_table, positive_int

PROG = "stg-train"

EPILOG = """examples:
  stg-train --demo --out demo/                  synthetic scene -> train on the CPU -> model, metrics, video
  stg-train scenes/coffee --out runs/coffee --iterations 30000 --device cuda
  stg-train scenes/coffee --out runs/coffee --resume      continue from runs/coffee/checkpoint.pt
  stg-train scenes/long --out runs/long --segments 0-2    first three 50-frame segments (others elsewhere)
  stg-train /shared/long --out /shared/runs/long --ray --device cuda   every segment as a task on a Ray cluster
  stg-train scenes/long --out runs/long --gpus auto --device cuda      segments in parallel on this machine's GPUs

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


def _segment_list(text: str) -> list[int]:
    try:
        return parse_segment_list(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def _port(text: str) -> int:
    if not text.isdigit() or int(text) > 65535:
        raise argparse.ArgumentTypeError(f"a port is a number 0..65535, got {text!r}")
    return int(text)


def build_parser() -> argparse.ArgumentParser:
    d = TrainConfig()
    p = argparse.ArgumentParser(
        prog=PROG, epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Learn Spacetime Gaussians from synchronised multi-view video and write a .stg model.")
    p.add_argument("data", nargs="?", metavar="DATA", help="dataset folder (see below); omit with --demo")
    p.add_argument("--out", metavar="DIR", help="output folder (created if missing); required unless --demo "
                   "(default for --demo: stg-demo)")
    p.add_argument("--model", choices=["full", "lite"], default=d.model,
                   help="full: 9 features per Gaussian + colour decoder MLP (view- and time-dependent "
                        "colour); lite: plain rgb, smaller and faster (default %(default)s)")
    p.add_argument("--iterations", type=positive_int, default=None, metavar="N",
                   help=f"optimisation steps; the density-control schedule is stretched to N (default {d.iterations}, "
                        "the demo's own default with --demo)")
    p.add_argument("--splatter", choices=["auto", "numba", "torch", "gsplat"], default="auto",
                   help="rasteriser: numba = the fast CPU splatter (numba kernels with a backward pass); torch = "
                        "the readable reference splatter in plain torch (CPU and CUDA); gsplat = the gsplat "
                        "library's CUDA kernels (pip install -e \".[cuda]\"; needs --device cuda); auto = numba "
                        "on the CPU, gsplat on CUDA when it can run, else torch (default auto)")
    p.add_argument("--device", choices=["cpu", "cuda"], default="cpu",
                   help="where the parameters live and rendering runs (default cpu)")
    p.add_argument("--resume", action="store_true",
                   help="continue from OUT/checkpoint.pt with its settings (a killed run resumed this way "
                        "reaches the same state as an uninterrupted one); starts afresh if there is none")
    p.add_argument("--segment-frames", type=positive_int, default=50, metavar="N",
                   help="frames per segment: a longer video is trained as consecutive independent models of N "
                        "frames (a last piece under N/2 frames joins the segment before it), one folder "
                        "OUT/segments/NN each, merged into OUT/model.stg (default %(default)s, as the paper)")
    p.add_argument("--segments", type=_segment_list, default=None, metavar="LIST",
                   help="train only these segments, indices from 0: e.g. 2,3 or 0-2 (default: all); run "
                        "the others elsewhere, copy their OUT/segments/NN folders into OUT/segments, and "
                        "--resume (or stg-convert merge) writes OUT/model.stg; with --resume, finished "
                        "segments are kept and an unfinished one continues from its checkpoint")
    parallel = p.add_mutually_exclusive_group()
    parallel.add_argument("--ray", nargs="?", const="auto", default=None, metavar="ADDRESS",
                          help="train the segments in parallel as tasks on a Ray cluster: ADDRESS (host:port or "
                               "ray://host:port), or auto (the default when the flag has no value: RAY_ADDRESS, "
                               "else a cluster started here with `ray start`, else a new local Ray); one GPU per "
                               "segment with --device cuda, else --threads CPUs (default 1). DATA and OUT must be "
                               "on storage every node sees (checked). Needs pip install -e \".[distributed]\"; "
                               "see docs/distributed.md")
    parallel.add_argument("--gpus", default=None, metavar="auto|LIST",
                          help="train the segments in parallel on the GPUs of this machine, one worker process "
                               "per GPU: auto (every GPU) or indices such as 0,1 (needs --device cuda)")
    p.add_argument("--checkpoint-every", type=positive_int, default=d.checkpoint_every, metavar="N",
                   help="write OUT/checkpoint.pt (atomically) every N steps and at the end (default %(default)s)")
    p.add_argument("--batch", type=positive_int, default=d.batch, metavar="B",
                   help="training views per step, all at one random time (default %(default)s)")
    p.add_argument("--points", type=positive_int, default=None, metavar="N",
                   help="initial Gaussians: the most SfM points kept (a random subset beyond), or the number "
                        f"sampled in the cameras' common view volume (default {d.num_points}, the demo's "
                        f"{DEMO_TRAINING['num_points']} with --demo)")
    p.add_argument("--init", choices=METHODS, default="auto",
                   help="initial points: sfm = SIFT features matched and triangulated with the known poses "
                        "(pycolmap, CPU) on every --init-every'th frame, cached in DATA/.stg_cache/sfm; volume = "
                        "sampled in the cameras' common view volume at photo-consistent depths between the "
                        "near/far depth bounds; combined = the SfM points plus volume samples where they leave "
                        "the training images uncovered; sfm and combined fall back to volume with a warning when "
                        "SfM finds too few points; auto = volume (default). Bounds: --near/--far, else the layout's "
                        "(N3V), else the COLMAP model's points, else the SfM points (SfM then runs for them)")
    p.add_argument("--init-every", type=positive_int, default=1, metavar="N",
                   help="run SfM on every N-th frame (default %(default)s: every frame, as the paper)")
    p.add_argument("--motion-init", choices=MOTION_INITS, default=d.motion_init,
                   help="initial motion of the Gaussians: flow = each initial point's velocity triangulated from "
                        "the optical flow of its frame in the training cameras that see it (points whose flow is "
                        "under half a pixel stay at rest); zero = at rest, as the reference implementation "
                        "(default %(default)s; docs/dynamic.md compares them)")
    p.add_argument("--seed", type=int, default=d.seed, help="random seed (default %(default)s)")
    add_dataset_options(p, depth_bounds=True)
    p.add_argument("--threads", type=positive_int, default=None, metavar="N",
                   help="CPU threads for torch and the numba splatter (default: the cores; with --ray, the CPUs "
                        "and threads of each segment's task, default 1; with --gpus, each worker's threads)")
    p.add_argument("--no-check", action="store_true",
                   help="skip comparing the runtime's render of the exported file with the trainer's")
    p.add_argument("--no-guided", action="store_true",
                   help="no guided sampling (new Gaussians along the rays of high-error patches, the paper's "
                        "Sec. 4.4; on by default)")
    p.add_argument("--viewer", nargs="?", type=_port, const=8080, default=None, metavar="PORT",
                   help="show the model in the browser while it trains, at http://127.0.0.1:PORT (default "
                        "8080; needs the viewer extra): the current parameters every few seconds, and the "
                        "step, loss, PSNR and Gaussians (docs/viewer.md)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--demo", action="store_true",
                   help=f"generate the synthetic scene ({DEMO_SCENE['cameras']} cameras x {DEMO_SCENE['frames']} "
                        f"frames, {DEMO_SCENE['width']}x{DEMO_SCENE['height']}) into OUT/data, train on it, "
                        "evaluate, and write OUT/model.stg, OUT/metrics.json and a novel-view video OUT/orbit.mp4")
    return p


def _config(args, splatter: str) -> TrainConfig:
    """The run's settings from the arguments (the demo's defaults with --demo)."""
    base = TrainConfig(**DEMO_TRAINING) if args.demo else TrainConfig()
    base.model, base.batch, base.seed, base.device = args.model, args.batch, args.seed, args.device
    base.checkpoint_every, base.splatter = args.checkpoint_every, splatter
    base.guided, base.init_every, base.init = not args.no_guided, args.init_every, args.init
    base.motion_init = args.motion_init
    if args.iterations:
        base.iterations = args.iterations
    if args.points:
        base.num_points = args.points
    return base


def main(argv=None) -> int:
    """Entry point of `stg-train`."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if not args.demo and args.data is None:
        parser.error("give a DATA folder (or --demo)")
    if not args.demo and args.out is None:
        parser.error("--out DIR is required")
    check_dataset_options(parser, args)
    if (args.ray is not None or args.gpus is not None) and args.demo:
        parser.error("--ray and --gpus train a DATA folder, not --demo")
    if args.gpus is not None and args.device != "cuda":
        return error(PROG, "--gpus trains on GPUs: add --device cuda (or use --ray for CPU workers)")
    try:
        splatter = resolve_backend(args.splatter, args.device)
    except ValueError as e:
        return error(PROG, str(e))
    import torch

    if args.device == "cuda" and args.ray is None and not torch.cuda.is_available():
        return error(PROG, "--device cuda: torch sees no CUDA device")
    if args.threads:
        set_cpu_threads(args.threads)
    config = _config(args, splatter)
    options = dict(resume=args.resume, quiet=args.quiet, check=not args.no_check,
                   segment_frames=args.segment_frames, segments=args.segments)
    if args.viewer is not None:
        try:
            from ..viewer import TrainingViewer
            options["callback"] = TrainingViewer(args.viewer, quiet=args.quiet)
        except ImportError as e:
            return error(PROG, f"--viewer needs the viewer extra (python -m pip install -e \".[viewer]\"): {e}")
        except OSError as e:  # the port is taken
            return error(PROG, f"--viewer: {e}")
    start = time.perf_counter()
    try:
        if args.demo:
            out = Path(args.out or "stg-demo")
            metrics = run_demo(out, config, **options)
        else:
            dataset = load_dataset(args.data, lazy=True, **dataset_options(args))
            if args.ray is not None or args.gpus is not None:
                from ..distributed.run import train_parallel

                metrics = train_parallel(dataset, Path(args.out), config, ray=args.ray, gpus=args.gpus,
                                         threads=args.threads, **options)
            else:
                metrics = train(dataset, Path(args.out), config, **options)
    except (DataError, SegmentError, RenderError, DistributedError) as e:
        return error(PROG, str(e))
    finally:
        if options.get("callback") is not None:
            options["callback"].close()
    if metrics.get("missing_segments"):
        return 0  # OUT/model.stg waits for the other segments (the pipeline said which)
    print(format_table(metrics["heldout"], metrics["file_bytes"], metrics["gaussians"]))
    if args.demo:
        print(f"demo done in {time.perf_counter() - start:.0f} s: {out / 'model.stg'}, {out / 'metrics.json'}, "
              f"{out / 'orbit.mp4'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
