"""`stg-convert`: compress models, import other tools' models, export snapshots, merge segments.

A thin command line over stg_train.convert.{compress, reference, gaussians3d, merge}. Every problem
with an input prints `stg-convert: error: <file>: <problem>` and exits with code 2; outputs are written
atomically, so a failed run leaves no output file behind. More subcommands come from COMMANDS, each in
its own module.
"""
from __future__ import annotations

import argparse
import importlib
import os
import sys
import warnings

from .common import Parser, error, finite_float, nonnegative_int, positive_float, positive_int

#: The compression presets (stg_train.convert.compress.PRESETS) and fine-tuning's pruning stages
#: (stg_train.convert.finetune.PRUNE_STAGES), checked by tests/convert/test_finetune.py, named here so
#: that --help does not import the compressor (or torch).
PRESET_NAMES = ("lossless", "balanced", "small", "web")
PRUNE_STAGES = 5

PROG = "stg-convert"

#: The subcommands that live in a module of their own, listed after the others: name -> module, whose
#: docstring is the subcommand's description (its first line the help of `stg-convert --help`), whose
#: add_arguments(parser) declares its arguments and whose run(args) -> exit code runs it (the errors
#: main catches become `stg-convert: error:` lines). The module is imported when the parser is built:
#: it imports nothing heavy at its top. docs/extending.md adds one.
COMMANDS: dict[str, str] = {}

EPILOG = """examples:
  stg-convert compress run/model.stg run/model.small.stg --preset small
  stg-convert compress model.stg out.stg --preset balanced --encoding position=u16,features=u8 --data scene/
  stg-convert import-reference seg0/point_cloud.ply seg1/point_cloud.ply out.stg \\
      --decoder seg0/decoder.pth seg1/decoder.pth --fps 30
  stg-convert import-3dgs point_cloud.ply scene.stg
  stg-convert export-ply model.stg snapshot.ply --time 1.5
  stg-convert merge part0.stg part1.stg whole.stg
  stg-convert export-web model.stg site/        (then: python -m http.server -d site)

Exit codes: 0 done, 2 bad input or arguments (nothing written)."""

COMPRESS_EPILOG = """presets (the options below override them):
  lossless  float32, no pruning, original order, zlib level 9 (the same model, a slightly smaller file)
  balanced  target: <= 1/4 of the float32 file, <= 0.1 dB PSNR loss. Drops Gaussians whose peak
            opacity stays below 1/255 (never drawn) or that no camera of the file sees, Morton order,
            per attribute the cheapest encoding (u8, u16, f16, f32) within the error budget
  small     target: <= 1/8 of the float32 file, <= 0.5 dB loss; also drops peak opacity < 0.01
  web       <= 0.3 dB loss, the smallest file (format 1.5: readers of 1.4 and older refuse it): as
            small, also drops the least important Gaussians within part of the budget, each channel
            group arithmetic-coded on its own, as differences where that is smaller

The error budget is measured by rendering: the file's cameras at the first, middle and last frame of
each segment, or with --data the dataset's held-out camera against its ground truth. The report lists
Gaussians and bytes per attribute before and after, and the PSNR change."""


def _file_error(path, e: OSError) -> str:
    return f"{e.filename or path}: {e.strerror or e}"


def _writable(path, inputs=()) -> str:
    """`path` if its folder exists, it is not a folder and it is none of `inputs` (checked before any
    work; leftovers of an interrupted write of it are removed); ValueError naming it otherwise."""
    from stg_runtime.atomic import remove_leftovers

    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        raise ValueError(f"{path}: cannot write: the folder {folder} does not exist")
    if os.path.isdir(path):
        raise ValueError(f"{path}: is a folder; name the file to write")
    for source in inputs:
        if os.path.abspath(source) == os.path.abspath(path) or (
                os.path.exists(path) and os.path.exists(source) and os.path.samefile(source, path)):
            raise ValueError(f"{path}: is also an input; write the output to another file")
    remove_leftovers(folder, os.path.basename(path))
    return path


def _level(text: str) -> int:
    value = int(text) if text.isdigit() else -1
    if not 0 <= value <= 9:
        raise argparse.ArgumentTypeError(f"zlib level must be 0-9, got {text!r}")
    return value


def _fraction(text: str) -> float:
    value = finite_float(text)
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"must be in [0, 1], got {text!r}")
    return value


def _unit_fraction(text: str) -> float:
    value = _fraction(text)
    if value >= 1.0:
        raise argparse.ArgumentTypeError(f"must be below 1, got {text}")
    return value


def _positive_list(kind, what: str):
    """An argument type: one positive `kind` (`what`, plural) or a comma-separated list of them."""
    def parse(text: str) -> list:
        try:
            values = [kind(v) for v in text.split(",")]
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {what}, one or a comma-separated list, got {text!r}") from None
        if min(values) <= 0:
            raise argparse.ArgumentTypeError(f"{what} must be positive, got {text!r}")
        return values
    return parse


_frames = _positive_list(int, "frame counts")
_durations = _positive_list(float, "durations")


def build_parser() -> argparse.ArgumentParser:
    fmt = argparse.RawDescriptionHelpFormatter
    from stg_runtime.model import ACTIVATIONS, ATTRIBUTES  # numpy only

    p = Parser(prog=PROG, epilog=EPILOG, formatter_class=fmt,
                                description="Shrink .stg models, bring models from other tools into the "
                                            ".stg format, export static snapshots, merge segments.")
    sub = p.add_subparsers(dest="command", metavar="COMMAND", required=True)

    c = sub.add_parser("compress", help="prune, reorder and quantize a model; prints a report",
                       description="Write a smaller copy of a .stg model and print what changed.",
                       epilog=COMPRESS_EPILOG, formatter_class=fmt)
    c.add_argument("input", metavar="IN.stg")
    c.add_argument("output", metavar="OUT.stg")
    c.add_argument("--preset", choices=PRESET_NAMES, default="balanced", help="default %(default)s")
    c.add_argument("--encoding", action="append", default=[], metavar="ATTR=MODE",
                   help=f"fix an attribute's encoding, MODE one of f32, f16, u16, u8; ATTR one of "
                        f"{', '.join(ATTRIBUTES)}; repeat or separate with commas (position=u16,features=u8)")
    c.add_argument("--prune-opacity", type=_fraction, default=None, metavar="X",
                   help="drop Gaussians whose peak opacity over their segment stays below X (0: keep all)")
    c.add_argument("--prune-unseen", action=argparse.BooleanOptionalAction, default=None,
                   help="drop Gaussians that no camera stored in the file sees at any frame")
    c.add_argument("--order", choices=["morton", "none"], default=None,
                   help="order of the Gaussians in the file: morton (Z-order of positions, compresses "
                        "better) or none (keep)")
    c.add_argument("--level", type=_level, default=None, metavar="N", help="zlib level 0-9 (presets: 9)")
    c.add_argument("--data", metavar="DATASET",
                   help="dataset folder (N3V layout) the model was trained on: measure the PSNR change "
                        "on its held-out camera against the ground truth")
    c.add_argument("--downscale", type=positive_int, default=1, metavar="K",
                   help="with --data: divide the frames' size by K, as in training (default 1)")
    c.add_argument("--finetune", type=positive_int, default=None, metavar="N",
                   help="with --data: prune, then fine-tune N steps against the training frames before "
                        "quantizing (docs/convert.md, 'Fine-tuning'; needs torch)")
    c.add_argument("--prune-fraction", type=_unit_fraction, default=0.3, metavar="F",
                   help="with --finetune: the fraction of Gaussians dropped, those that contribute least to "
                        "the training views (default 0.3)")
    c.add_argument("--prune-stages", type=positive_int, default=PRUNE_STAGES, metavar="K",
                   help="with --finetune: drop them in K equal shares over the first half of the steps, "
                        "ranked again each time (default %(default)s; 1: all before the first step)")
    c.add_argument("--still", type=_fraction, default=0.0, metavar="D",
                   help="with --finetune: Gaussians whose centre moves less than D x the training cameras' "
                        "extent while drawn lose their motion and rotation velocity, which the web preset "
                        "then stores almost for free (default 0: none; docs/convert.md, 'Still Gaussians')")
    c.add_argument("--finetune-quantised", type=positive_int, default=None, metavar="M",
                   help="with --finetune: then fine-tune M more steps through fake quantisation one step "
                        "below the bits the preset chose and search again; the smaller file within the "
                        "preset's loss is written (docs/convert.md, 'Fine-tuning')")

    r = sub.add_parser("import-reference", formatter_class=fmt,
                       help="import models of the paper's reference implementation (PLY + decoder)",
                       description="Convert the reference implementation's trained models (one PLY per "
                                   "segment, in time order, and for full models the decoder state dict "
                                   "of each) into one .stg file. The reference's time t = frame / duration "
                                   "(its training setting, 50 by default) is mapped to ours (frame / "
                                   "segment frames).")
    r.add_argument("inputs", nargs="+", metavar="PLY", help="the segments' PLYs, in time order")
    r.add_argument("output", metavar="OUT.stg")
    r.add_argument("--decoder", nargs="+", default=None, metavar="PT",
                   help="decoder state dict (torch, read with weights_only) of each PLY, same order, "
                        "after the files; full models only (reading needs torch)")
    r.add_argument("--fps", type=positive_float, default=30.0, help="frames per second (default %(default)s)")
    r.add_argument("--start-frame", type=nonnegative_int, default=0, metavar="N",
                   help="video frame of the first segment's first frame (default 0)")
    r.add_argument("--segment-frames", type=_frames, default=[50], metavar="F[,F...]",
                   help="frames per segment: one count for all, or one per PLY (e.g. 50,50,20; default 50)")
    r.add_argument("--duration", type=_durations, default=[50.0], metavar="D[,D...]",
                   help="the reference's `duration` each PLY was trained with (frame j at t = j / D): one for "
                        "all, or one per PLY (default 50, the official default; a short last segment trained "
                        "with its own length, e.g. 50,50,20)")
    r.add_argument("--activation", choices=list(ACTIVATIONS), default="sigmoid",
                   help="decoder output activation: sigmoid (N3V), clamp (Technicolor), identity (Google "
                        "Immersive); default %(default)s")

    g = sub.add_parser("import-3dgs", help="import a static 3D Gaussian Splatting PLY (INRIA layout)",
                       description="Convert a static 3DGS PLY (x y z nx ny nz f_dc_0..2 f_rest_* opacity "
                                   "scale_0..2 rot_0..3) into a .stg model with spherical-harmonics colour, "
                                   "no motion and constant opacity.")
    g.add_argument("input", metavar="PLY")
    g.add_argument("output", metavar="OUT.stg")
    g.add_argument("--fps", type=positive_float, default=30.0, help="frames per second (default %(default)s)")
    g.add_argument("--frames", type=positive_int, default=1, metavar="N", help="frames the static model covers (default 1)")
    g.add_argument("--cameras", metavar="JSON",
                   help="3DGS cameras.json to store as the model's cameras (default: the one of the 3DGS "
                        "output folder, when found)")

    e = sub.add_parser("export-ply", help="write a static snapshot at one time as a 3DGS PLY",
                       description="Evaluate the model at --time and write the Gaussians as a 3DGS PLY "
                                   "(INRIA layout) for existing 3DGS viewers.")
    e.add_argument("input", metavar="IN.stg")
    e.add_argument("output", metavar="OUT.ply")
    e.add_argument("--time", type=finite_float, required=True, metavar="SECONDS", help="time of the snapshot")

    m = sub.add_parser("merge", help="join files whose segments follow each other",
                       description="Join .stg files holding consecutive segments (same kind and fps, no "
                                   "gaps or overlaps) into one multi-segment file.")
    m.add_argument("inputs", nargs="+", metavar="IN.stg", help="files to join (any order)")
    m.add_argument("output", metavar="OUT.stg")
    m.add_argument("--crossfade", type=nonnegative_int, default=None, metavar="B",
                   help="crossfade every seam over B frames, at most twice the context frames its two segments "
                        "were fitted to beyond it (stg-train --segment-context); 0: hard cuts (default: the "
                        "context both have, so each renders only the inner half of its context)")

    w = sub.add_parser("export-web", help="write a folder that plays the model in any browser",
                       description="Write OUT/index.html, the web player's JavaScript and a copy of the model: a "
                                   "self-contained folder for any static web host, offline too (python -m "
                                   "http.server -d OUT, then open http://localhost:8000). docs/web.md tells how "
                                   "to embed the player in another page.")
    w.add_argument("input", metavar="MODEL.stg")
    w.add_argument("output", metavar="OUT", help="folder to write (created when missing)")

    for name, module in COMMANDS.items():
        command = importlib.import_module(module)
        doc = (command.__doc__ or "").strip()
        command.add_arguments(sub.add_parser(name, help=doc.splitlines()[0] if doc else None, description=doc or None,
                                             formatter_class=fmt))
    return p


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    handlers = {"compress": _compress, "import-reference": _import_reference, "import-3dgs": _import_3dgs,
                "export-ply": _export_ply, "merge": _merge,
                "export-web": _export_web}
    handlers.update({name: _command for name in COMMANDS})
    from stg_runtime.format import FormatError
    from stg_runtime.player import RenderError

    from ..convert.ply import PLYError
    from ..data import DataError

    try:
        return handlers[args.command](args, parser)
    except (FormatError, PLYError, DataError, RenderError, ValueError) as e:
        return error(PROG, str(e))
    except OSError as e:
        return error(PROG, _file_error("", e))


def _command(args, parser) -> int:
    return importlib.import_module(COMMANDS[args.command]).run(args)


def _compress(args, parser) -> int:
    from ..convert.compress import compress_file, parse_encodings
    from ..data import load_dataset

    _writable(args.output, [args.input])
    encodings = {}
    for text in args.encoding:
        try:
            encodings.update(parse_encodings(text))
        except ValueError as e:
            return error(PROG, f"--encoding: {e}")
    overrides = {"encodings": encodings}
    if args.prune_opacity is not None:
        overrides["prune_opacity"] = args.prune_opacity or None
    if args.prune_unseen is not None:
        overrides["prune_unseen"] = args.prune_unseen
    if args.order is not None:
        overrides["order"] = None if args.order == "none" else args.order
    if args.level is not None:
        overrides["level"] = args.level
    if args.finetune_quantised is not None and args.finetune is None:
        return error(PROG, "--finetune-quantised needs --finetune (and --data)")
    if args.prune_stages != PRUNE_STAGES and args.finetune is None:
        return error(PROG, "--prune-stages needs --finetune (and --data)")
    if args.still and args.finetune is None:
        return error(PROG, "--still needs --finetune (and --data)")
    if args.finetune is not None and not args.data:
        return error(PROG, "--finetune needs --data (the frames to fine-tune against)")
    if args.finetune is not None and (encodings or len(overrides) > 1):
        return error(PROG, "--finetune takes the preset's settings: --encoding, --prune-opacity, "
                           "--[no-]prune-unseen, --order and --level are not applied with it")
    dataset = None
    if args.data:
        dataset = load_dataset(args.data, downscale=args.downscale)
    if args.finetune is not None:
        from ..convert.finetune import finetune_file

        report, info = finetune_file(args.input, args.output, dataset, args.finetune, args.preset,
                                     args.prune_fraction, quantised_steps=args.finetune_quantised or 0,
                                     stages=args.prune_stages, still=args.still)
        print(report.format())
        print(info.format())
        print(f"wrote {args.output}")
        return 0
    report = compress_file(args.input, args.output, args.preset, dataset=dataset, **overrides)
    print(report.format())
    print(f"wrote {args.output}")
    return 0


def _import_reference(args, parser) -> int:
    from stg_runtime import format as stg_format

    from ..convert.reference import import_reference

    plys, out = args.inputs, _writable(args.output, [*args.inputs, *(args.decoder or [])])
    frames = args.segment_frames[0] if len(args.segment_frames) == 1 else args.segment_frames
    durations = args.duration[0] if len(args.duration) == 1 else args.duration
    model = import_reference(plys, args.decoder, fps=args.fps, start_frame=args.start_frame,
                             segment_frames=frames, activation=args.activation, duration=durations)
    stg_format.save(model, out)
    count = sum(s.count for s in model.segments)
    print(f"wrote {out}: {model.kind} model, {len(model.segments)} segment(s), {model.num_frames} frames at "
          f"{model.fps:g} fps, {count} Gaussians")
    return 0


def _import_3dgs(args, parser) -> int:
    from stg_runtime import format as stg_format

    from ..convert.gaussians3d import import_3dgs_ply

    _writable(args.output, [args.input, *([args.cameras] if args.cameras else [])])
    model = import_3dgs_ply(args.input, fps=args.fps, num_frames=args.frames, cameras=args.cameras)
    stg_format.save(model, args.output)
    print(f"wrote {args.output}: {model.segments[0].count} Gaussians, {len(model.cameras)} cameras")
    return 0


def _export_ply(args, parser) -> int:
    from stg_runtime import format as stg_format

    from ..convert.gaussians3d import export_ply

    _writable(args.output, [args.input])
    model = stg_format.load(args.input)
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            count = export_ply(model, args.output, args.time)
        for w in caught:
            print(f"stg-convert: warning: {w.message}", file=sys.stderr)
    except ValueError as e:
        if str(e).startswith("t ="):
            return error(PROG, f"{args.input}: --time {args.time}: {e}")
        raise
    print(f"wrote {args.output}: {count} Gaussians at t = {args.time:g} s")
    return 0


def _merge(args, parser) -> int:
    from ..convert.merge import merge_files

    inputs, out = args.inputs, _writable(args.output, args.inputs)
    model = merge_files(inputs, out, crossfade=args.crossfade)
    fades = [s.crossfade_frames for s in model.segments[1:]]
    said = f", crossfades {fades} frames" if any(fades) else ""
    print(f"wrote {out}: {len(model.segments)} segments, {model.num_frames} frames, "
          f"{sum(s.count for s in model.segments)} Gaussians{said}")
    return 0


def _export_web(args, parser) -> int:
    from stg_runtime.web.export import export_web  # the player's files, only for this command
    written = export_web(args.input, args.output)
    print(f"wrote {args.output}: {', '.join(p.name for p in written)}\n"
          f"serve it with: python -m http.server -d {args.output}  (then open http://localhost:8000)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
