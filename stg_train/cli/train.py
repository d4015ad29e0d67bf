"""`stg-train`: learn Spacetime Gaussians from a dataset folder (or the built-in demo scene)."""
from __future__ import annotations

import argparse
import shlex
import sys
import time
from pathlib import Path

from ..choices import INIT_METHODS, MOTION_INITS, SEGMENT_SCHEDULES, SPLATTERS
from ..config import DEMO_SCENE, DEMO_TRAINING, TrainConfig
from ..rig.lens import known_falloff
from .common import (Parser, add_dataset_options, check_dataset_options, dataset_options, error, format_table,
                     given_options, nonnegative_int, port, positive_int)

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
A folder of raw videos (one per camera: mp4, mov, mkv, avi, webm, or a folder of frames; no poses) is
first prepared into OUT/prep/ as stg-prep does (synchronised, calibrated, in the rig layout), and trained
from there; a later run with the same videos reuses OUT/prep/.
--test-camera NAME holds out another camera; --fps sets the frame rate of layouts without one (default 30).
Writes OUT/model.stg (the player's file), OUT/checkpoint.pt and OUT/metrics.json. A video longer than
--segment-frames is trained as consecutive segments, each in OUT/segments/NN/ (checkpoint.pt, model.stg,
metrics.json), merged into one OUT/model.stg once every segment is trained; each segment starts from the
one before it with --segment-schedule warm, and is also fitted to --segment-context frames of its
neighbours, and players crossfade over the seams (docs/training.md, "Seams").

Defaults, against the paper's reference code (measured in docs/training.md, "Deviations from the
reference"): the model's formulas, the losses and the densification statistic (each view's
screen-gradient norm, averaged over the views that see a Gaussian, as gsplat does; it does not depend
on --batch) are the reference's. Ours, each kept because the reference's measured no better:
view-volume initial points (--init; the reference uses SfM), initial motion from the optical flow
(--motion-init; the reference starts at zero), learning rates stretched to --iterations (the
reference's are set for 30000 steps), guided sampling at the error patch's median depth after one
poor view (the reference: the view's maximum depth, two views), pruning applied at densification,
scale learning rate 0.005 (the reference's N3V configurations: 0.003), no rotation/motion separation,
each segment's first and last 3 frames drawn three times as often and the video's own first and last
frames six times (--edge-weight; the reference draws every frame alike).
Exit codes: 0 done, 2 bad data or arguments."""


def _segment_list(text: str) -> list[int]:
    from ..segments import parse_segment_list

    try:
        return parse_segment_list(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def _edge_weight(text: str) -> float:
    """W -> float, refused outside [1, 10] (below 1 the ends would be drawn less than the others; far
    above, they would take most of the run's steps)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number from 1 to 10, got {text!r}") from None
    if not 1 <= value <= 10:  # also refuses nan
        raise argparse.ArgumentTypeError(f"expected a number from 1 to 10, got {text!r}")
    return value


def _lens_falloff(text: str) -> tuple[float, float] | str | None:
    """K1[,K2] -> (k1, k2), checked by lens.known_falloff (the brightness within (0, 2] over the image);
    "auto" stays "auto" (measured before training); "none" -> None."""
    if text == "auto":
        return text
    if text == "none":
        return None
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected K1 or K1,K2 (numbers), auto or none, got {text!r}") from None
    try:
        return known_falloff(values)
    except ValueError as e:
        raise argparse.ArgumentTypeError(f"{e} (from {text!r})") from None


#: TrainConfig field -> the option that sets it (what a resumed run names when it refuses or applies one).
CONFIG_OPTIONS = {"model": "--model", "iterations": "--iterations", "batch": "--batch", "num_points": "--points",
                  "init": "--init", "init_every": "--init-every", "motion_init": "--motion-init", "seed": "--seed",
                  "checkpoint_every": "--checkpoint-every", "guided": "--no-guided", "device": "--device",
                  "splatter": "--splatter", "appearance": "--appearance", "pose_refine": "--pose-refine",
                  "segment_context": "--segment-context", "lens_falloff": "--lens-falloff",
                  "edge_weight": "--edge-weight", "segment_schedule": "--segment-schedule"}
#: argparse dest -> TrainConfig field, where they differ.
_DEST_FIELDS = {"points": "num_points", "no_guided": "guided"}


def build_parser() -> argparse.ArgumentParser:
    d = TrainConfig()
    p = Parser(
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
    p.add_argument("--splatter", choices=["auto", *SPLATTERS], default="auto",
                   help="rasteriser: numba = the fast CPU splatter (numba kernels with a backward pass); torch = "
                        "the readable reference splatter in plain torch (CPU and CUDA); gsplat = the gsplat "
                        "library's CUDA kernels (pip install -e \".[cuda]\"; needs --device cuda); auto = numba "
                        "on the CPU, gsplat on CUDA when it can run, else torch (default auto)")
    p.add_argument("--device", choices=["cpu", "cuda"], default="cpu",
                   help="where the parameters live and rendering runs (default cpu)")
    p.add_argument("--resume", action="store_true",
                   help="continue from OUT/checkpoint.pt with its settings (a killed run resumed this way "
                        "reaches the same state as an uninterrupted one); starts afresh if there is none. "
                        "--iterations, --checkpoint-every, --threads, --device, --splatter, --viewer and --quiet "
                        "may change (the run says so); --model, --batch, --points, --init, --init-every, "
                        "--motion-init, --seed and --no-guided must match the checkpoint's")
    p.add_argument("--force", action="store_true",
                   help="train from scratch even where OUT holds a run, replacing its checkpoint.pt, model.stg and "
                        "metrics.json (without --force or --resume such a run is refused)")
    p.add_argument("--segment-frames", type=positive_int, default=50, metavar="N",
                   help="frames per segment: a longer video is trained as consecutive independent models of N "
                        "frames (a last piece under N/2 frames joins the segment before it), one folder "
                        "OUT/segments/NN each, merged into OUT/model.stg (default %(default)s, as the paper)")
    p.add_argument("--segment-context", type=nonnegative_int, default=d.segment_context, metavar="C",
                   help="fit each segment also to up to C frames of its neighbours on either side (it still "
                        "shows only its own frames, and its run is lengthened by the share of context frames, "
                        "so its own frames get --iterations steps' worth); players then crossfade over every "
                        "seam where both neighbours have context, over C frames (format 1.3; 0: hard cuts "
                        "as before; default %(default)s; docs/training.md, \"Seams\")")
    p.add_argument("--edge-weight", type=_edge_weight, default=d.edge_weight, metavar="W",
                   help="draw each segment's first and last frames (3 at each end: the video's ends and the "
                        "frames next to a seam) W times as often as the others for a training step, and the "
                        "video's own first and last frames twice that: a segment's ends are otherwise its "
                        "weakest frames (1: every frame alike, as the reference; default %(default)s; "
                        "docs/training.md, \"Seams\")")
    p.add_argument("--segment-schedule", choices=SEGMENT_SCHEDULES, default=d.segment_schedule,
                   help="how a long video's segments start: warm (each from the previous segment's Gaussians "
                        "at the seam, re-expressed on its time axis, and its own initial points, trained for a "
                        "quarter of --iterations; the first cold) or independent (each from its own initial "
                        "points, as the paper); default %(default)s: warm segments are 3-6 dB worse inside "
                        "(docs/notes/warm-segments.md). (--segments picks which segments to train.)")
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
                               "segment with --device cuda, else --threads CPUs (1 when not given). DATA and OUT must be "
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
    p.add_argument("--init", choices=INIT_METHODS, default="auto",
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
    p.add_argument("--seed", type=nonnegative_int, default=d.seed, help="random seed (default %(default)s)")
    add_dataset_options(p, depth_bounds=True)
    p.add_argument("--threads", type=positive_int, default=None, metavar="N",
                   help="CPU threads for torch and the numba splatter (default: the cores; with --ray, the CPUs "
                        "and threads of each segment's task, default 1; with --gpus, each worker's threads)")
    p.add_argument("--no-check", action="store_true",
                   help="skip comparing the runtime's render of the exported file with the trainer's")
    p.add_argument("--no-guided", action="store_true",
                   help="no guided sampling (new Gaussians along the rays of high-error patches, the paper's "
                        "Sec. 4.4; on by default)")
    p.add_argument("--appearance", action=argparse.BooleanOptionalAction, default=d.appearance,
                   help="learn each training camera's colour transform (3x3 + bias, their mean held at the "
                        "identity) and lens vignetting, applied to its renders before the loss only: for "
                        "captures whose cameras disagree in exposure and colour; the .stg holds the canonical "
                        "scene. Default: on when the training cameras' colour gains, measured before training "
                        "from what neighbouring cameras see of the same surfaces, differ by more than 3 %% "
                        "(RMS), which stg-train prints; when the rig was measured so, a third of the way through "
                        "the gains are measured again through the model's own geometry, and set and hold each "
                        "camera's transform; --no-appearance: never (docs/training.md)")
    p.add_argument("--pose-refine", action=argparse.BooleanOptionalAction, default=d.pose_refine,
                   help="refine each training camera's pose (a small rotation and translation) with the scene; "
                        "writes OUT/refined_cameras.json, and the .stg stores the refined cameras. Default: on "
                        "when what neighbouring cameras see lies over 0.2 px (median, in pictures of at most "
                        "320 px) from the epipolar lines of the stated poses, which stg-train prints; "
                        "--no-pose-refine: never (docs/training.md)")
    p.add_argument("--lens-falloff", type=_lens_falloff, default=d.lens_falloff, metavar="K1[,K2]|auto|none",
                   help="the cameras' known vignetting, e.g. from a flat-field calibration or the lens profile: "
                        "brightness 1 + K1 s + K2 s^2, s the squared distance from the principal point over its "
                        "value at the farthest corner (-0.3: 30 %% darker at the corners), applied to every "
                        "training render before the loss, so the .stg holds the scene without it; with "
                        "--appearance, no vignetting is learned then; write --lens-falloff=-0.3,0.05 when "
                        "K1 is negative and K2 given. 'auto' (the default) measures it before training from "
                        "what neighbouring cameras see of the same surfaces at the same instant (seconds for the "
                        "demo's 12 cameras) and prints it; it trains without one where the cameras overlap too "
                        "little, their lenses differ or the corners are within 3 %% of the centre; a third of the "
                        "way through, it is measured again through the model's own geometry (printed after "
                        "training); "
                        "a resumed run keeps what its first run measured. 'none': no falloff "
                        "(docs/training.md)")
    p.add_argument("--viewer", nargs="?", type=port, const=8080, default=None, metavar="PORT",
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
    base.appearance, base.pose_refine = args.appearance, args.pose_refine
    base.segment_context, base.edge_weight = args.segment_context, args.edge_weight
    base.segment_schedule = args.segment_schedule
    base.lens_falloff = args.lens_falloff
    if args.iterations:
        base.iterations = args.iterations
    if args.points:
        base.num_points = args.points
    return base


def _given(args, dests: set[str]) -> dict[str, str]:
    """TrainConfig field -> its option and value as given (e.g. "--iterations 500") for the settings on the
    command line."""
    given = {}
    for dest in dests:
        name = _DEST_FIELDS.get(dest, dest)
        if name in CONFIG_OPTIONS:
            value = getattr(args, dest)
            given[name] = CONFIG_OPTIONS[name] + ("" if isinstance(value, bool) else f" {value}")
    return given


def _check_arguments(parser: argparse.ArgumentParser, args) -> None:
    """Every check that needs no data and no heavy import: parser.error (one line, exit 2)."""
    if args.demo and args.data is not None:
        parser.error(f"give a DATA folder or --demo, not both (got {args.data!r} and --demo)")
    if not args.demo and args.data is None:
        parser.error("give a DATA folder (or --demo)")
    if not args.demo and args.out is None:
        parser.error("--out DIR is required")
    if args.resume and args.force:
        parser.error("--resume continues the run in OUT, --force replaces it: give one")
    check_dataset_options(parser, args)
    if (args.ray is not None or args.gpus is not None) and args.demo:
        parser.error("--ray and --gpus train a DATA folder, not --demo")
    if (args.ray is not None or args.gpus is not None) and args.viewer is not None:
        parser.error(f"--viewer shows a run of this process, but with {'--ray' if args.ray is not None else '--gpus'} "
                     "the segments train in worker processes: leave out --viewer (or the parallel option)")


def _resume_command(argv) -> str:
    """The command line that continues this run: the same arguments, with --resume (and without --force)."""
    args = [a for a in (sys.argv[1:] if argv is None else argv) if a != "--force"]
    return shlex.join([PROG, *args, *([] if "--resume" in args else ["--resume"])])


def main(argv=None) -> int:
    """Entry point of `stg-train`."""
    parser = build_parser()
    args = parser.parse_args(argv)
    _check_arguments(parser, args)
    if args.gpus is not None and args.device != "cuda":
        return error(PROG, "--gpus trains on GPUs: add --device cuda (or use --ray for CPU workers)")
    given = _given(args, given_options(parser, argv))
    out = Path(args.out or "stg-demo")
    try:
        return _run(args, out, given, argv)
    except KeyboardInterrupt:  # outside the training steps (those stop cleanly: pipeline.Interrupted)
        ckpt = out / "checkpoint.pt"
        if ckpt.exists() or (out / "segments").is_dir():
            print(f"\n{PROG}: interrupted; continue with: {_resume_command(argv)}", file=sys.stderr)
        else:
            print(f"\n{PROG}: interrupted before the first checkpoint: nothing to resume", file=sys.stderr)
        return 130


def _prepared(args, out: Path) -> str:
    """DATA, or where a folder of raw videos given as DATA is prepared (OUT/prep, stg_train.prep), saying so."""
    from ..prep.inputs import is_raw_videos

    if args.layout != "auto" or not is_raw_videos(args.data):
        return args.data
    from stg_runtime.progress import progress_stages

    from ..data import DataError
    from ..prep import prepared

    target = out / "prep"
    if out.exists() and not out.is_dir():
        raise DataError(f"--out {out}: is a file, not a folder")
    try:
        with progress_stages(enabled=not args.quiet) as stage:
            report, reused = prepared(args.data, target, fps=args.fps, progress=stage, announce=lambda: print(
                f"{PROG}: {args.data} holds raw videos: preparing them into {target} (as stg-prep {args.data} "
                f"{target} does)", file=sys.stderr))
    except OSError as e:  # OUT cannot be written
        raise DataError(f"{e.filename or target}: {e.strerror or e}") from None
    if reused:
        print(f"{PROG}: {args.data} holds raw videos: reusing {target}, prepared from them before", file=sys.stderr)
    else:
        for warning in report["warnings"]:
            print(f"{PROG}: warning: {warning}", file=sys.stderr)
    return str(target)


def _run(args, out: Path, given: dict[str, str], argv) -> int:
    """Validate what needs the data and the heavy modules, then train; the exit code."""
    from stg_runtime.player import RenderError

    from ..data import DataError, load_dataset
    from ..distributed import DistributedError
    from ..pipeline import Interrupted, claim_output, run_demo, train
    from ..render import resolve_backend
    from ..segments import SegmentError
    from ..threads import set_cpu_threads

    try:
        splatter = resolve_backend(args.splatter, args.device)
    except ValueError as e:
        return error(PROG, f"--splatter {args.splatter}: {e}")
    if args.threads and args.ray is None:
        from numba import config as numba_config

        if args.threads > numba_config.NUMBA_NUM_THREADS:
            return error(PROG, f"--threads {args.threads}: this machine runs at most {numba_config.NUMBA_NUM_THREADS} "
                               "(numba's NUMBA_NUM_THREADS, the CPU threads)")
    import torch

    if args.device == "cuda" and args.ray is None and not torch.cuda.is_available():
        return error(PROG, "--device cuda: torch sees no CUDA device (train on the CPU with --device cpu)")
    config = _config(args, splatter)
    options = dict(resume=args.resume, quiet=args.quiet, check=not args.no_check,
                   segment_frames=args.segment_frames, segments=args.segments)
    start = time.perf_counter()
    viewer = None
    try:
        data = args.data if args.demo else _prepared(args, out)
        dataset = None if args.demo else load_dataset(data, lazy=True, **dataset_options(args))
        claim_output(out, dataset, args.segment_frames, args.segments, resume=args.resume, force=args.force)
        if args.threads:
            set_cpu_threads(args.threads)
            if args.resume and (out / "checkpoint.pt").exists() and not args.quiet:
                print(f"{PROG}: --threads {args.threads} applies to the resumed run", file=sys.stderr)
        if args.viewer is not None:
            try:
                from ..viewer import TrainingViewer
                viewer = TrainingViewer(args.viewer, quiet=args.quiet)
            except ImportError as e:
                return error(PROG, f"--viewer needs the viewer extra (python -m pip install -e \".[viewer]\"): {e}")
            except OSError as e:  # the port is taken
                return error(PROG, f"--viewer {args.viewer}: {e}: choose another with --viewer PORT")
        if args.demo:
            metrics = run_demo(out, config, callback=viewer, given=given, stop_on_signal=True, **options)
        elif args.ray is not None or args.gpus is not None:
            from ..distributed.run import train_parallel

            metrics = train_parallel(dataset, out, config, ray=args.ray, gpus=args.gpus, threads=args.threads,
                                     **options)
        else:
            metrics = train(dataset, out, config, callback=viewer, given=given, stop_on_signal=True, **options)
    except Interrupted as e:
        print(f"\n{PROG}: interrupted at step {e.step} of {e.iterations}; saved {e.checkpoint}; continue with: "
              f"{_resume_command(argv)}", file=sys.stderr)
        return 130
    except (DataError, SegmentError, RenderError, DistributedError) as e:
        return error(PROG, str(e))
    finally:
        if viewer is not None:
            viewer.close()
    if metrics.get("missing_segments"):
        return 0  # OUT/model.stg waits for the other segments (the pipeline said which)
    print(format_table(metrics["heldout"], metrics["file_bytes"], metrics["gaussians"]))
    if args.demo:
        print(f"demo done in {time.perf_counter() - start:.0f} s: {out / 'model.stg'}, {out / 'metrics.json'}, "
              f"{out / 'orbit.mp4'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
