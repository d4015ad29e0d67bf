"""`stg-eval`: evaluate a .stg model on the held-out camera of the dataset it was trained on."""
from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from .common import Parser, add_dataset_options, dataset_options, error, finite_float, format_table

PROG = "stg-eval"

EPILOG = """Renders the held-out camera(s) of DATA (cam00 for N3V; --test-camera to choose) at every frame through the runtime player
and compares with the ground truth: PSNR (dB), the colour-aligned PSNR (after one affine colour map,
3x3 + bias, per camera fitted over its frames: a held-out camera's own exposure and white balance not
counted), SSIM (scikit-image, data_range 1), DSSIM1 = (1 - SSIM)/2
with data_range 1 and DSSIM2 with data_range 2 (the paper's Sec. 6.1), LPIPS with AlexNet and VGG (the
optional lpips package: python -m pip install -e ".[lpips]"; its backbones download on first use; a
line on stderr says why when it is left out), render FPS, model size.

PSNR and SSIM are also given apart for the dynamic pixels (those whose ground truth changes over the
evaluated frames by more than --dynamic-threshold in some colour channel: moving objects, what appears
or vanishes, their shadows) and the static rest; docs/dynamic.md explains the measure.

With --align-poses, each held-out camera's pose is first aligned to its pictures against the model
(stg_train.rig.pose_align: Gauss-Newton over a rotation and a shift on 4 frames, an affine colour map
fitted alongside; the pose only is kept) and the line "CAM's pose aligned to its pictures: moved ..."
says how far; the JSON keeps the aligned poses under "aligned_poses". A real capture's held-out camera
is calibrated no better than its training cameras, and a model trained with pose refinement sits in a
frame of its own: aligned, the view is scored on what the model shows rather than on where the
calibration puts it, as pose-refining methods are scored (docs/training.md, "Real captures").

For a model of several segments, the seams too (docs/training.md, "Seams"): the worst boundary dip (the
interior frames' mean PSNR minus the lowest PSNR of a segment's first or last frame, dB) and the seam
flicker ratio (the temporal error mean |(R[j+1] - R[j]) - (G[j+1] - G[j])| across the worst seam over
that of the pairs inside segments; 1 means no pop)."""


def build_parser() -> argparse.ArgumentParser:
    from ..metrics import DYNAMIC_THRESHOLD  # numpy only

    p = Parser(prog=PROG, epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter,
                                description="Evaluate a .stg model on a dataset's held-out camera.")
    p.add_argument("model", metavar="MODEL", help="the .stg file")
    p.add_argument("data", metavar="DATA", help="the dataset folder it was trained on (any layout of stg-train)")
    p.add_argument("--json", metavar="PATH", help="also write the figures (and per-frame values) as JSON")
    add_dataset_options(p)
    p.add_argument("--dynamic-threshold", type=_fraction, default=DYNAMIC_THRESHOLD, metavar="X",
                   help="a pixel is dynamic when its ground truth changes by more than X (colour values in "
                        f"[0, 1]) over the frames (default {DYNAMIC_THRESHOLD:g})")
    p.add_argument("--no-lpips", action="store_true",
                   help="skip LPIPS (computed with AlexNet and VGG when the optional lpips package works)")
    p.add_argument("--any-cameras", action="store_true",
                   help="evaluate even when the model's stored cameras are not DATA's (by default such a model, "
                        "trained on other data, is refused)")
    p.add_argument("--align-poses", action="store_true",
                   help="first align each held-out camera's pose to its pictures against the model (a small "
                        "rotation and shift, on 4 frames; test-time pose optimisation, as pose-refining "
                        "methods are scored), and say how far it moved: for a capture whose held-out camera "
                        "is calibrated no better than its training cameras")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    return p


def _fraction(text: str) -> float:
    value = finite_float(text)
    if not 0 <= value <= 1:
        raise argparse.ArgumentTypeError(f"must be in [0, 1] (colour values), got {text!r}")
    return value


def main(argv=None) -> int:
    """Entry point of `stg-eval`."""
    args = build_parser().parse_args(argv)
    if args.json and (os.path.isdir(args.json) or str(args.json).endswith(("/", os.sep))):
        return error(PROG, f"--json {args.json}: is a folder; name the JSON file to write")
    if args.json and not os.path.isdir(os.path.dirname(os.path.abspath(args.json))):
        return error(PROG, f"--json {args.json}: the folder {os.path.dirname(os.path.abspath(args.json))} does not exist")
    if not os.path.isdir(args.data):
        return error(PROG, f"DATA {args.data}: {'is not a folder' if os.path.exists(args.data) else 'no such folder'}")
    from stg_runtime.format import FormatError
    from stg_runtime.player import Player, RenderError

    from ..data import DataError, load_dataset
    from ..metrics import evaluate_player, evaluate_seams, heldout, lpips_models
    from ..pipeline import align_heldout, check_cameras, model_frames

    try:
        player = Player(args.model, device="cpu")
    except IsADirectoryError:
        return error(PROG, f"{args.model}: is a folder, not a .stg model")
    except (OSError, FormatError) as e:
        return error(PROG, str(e) if isinstance(e, FormatError) else f"{args.model}: {e.strerror or e}")
    try:
        dataset = load_dataset(args.data, **dataset_options(args))
        frames = model_frames(player, dataset, args.model)
        if not args.any_cameras:
            check_cameras(player, dataset, args.model)
    except DataError as e:
        return error(PROG, str(e))
    if len(frames) < dataset.num_frames:  # a model of some segments only (stg-train --segments)
        print(f"{PROG}: {args.model} covers frames {frames.start}-{frames.stop - 1} of the dataset's "
              f"{dataset.num_frames}: evaluating those", file=sys.stderr)
    lpips, why = ({}, None) if args.no_lpips else lpips_models()
    if why:
        print(f"{PROG}: {why}", file=sys.stderr)
    aligned = {}
    try:
        if args.align_poses:
            dataset, aligned = align_heldout(player, dataset, frames, quiet=args.quiet)
            for name, a in aligned.items():
                print(f"{PROG}: {name}'s pose aligned to its pictures: moved {a.rotation_deg:.3f} degrees and "
                      f"{a.shift:.3g} units (mean squared error {a.mse_before:.3g} -> {a.mse_after:.3g}, "
                      f"colour map fitted)", file=sys.stderr)
        result = evaluate_player(player, dataset, frames=frames, lpips=lpips, threshold=args.dynamic_threshold)
    except RenderError as e:
        return error(PROG, str(e))
    seams = evaluate_seams(result, [s.start_frame for s in player.model.segments])
    size = Path(args.model).stat().st_size
    count = sum(s.count for s in player.model.segments)
    print(format_table(result, size, count))
    summary = heldout(result)
    summary.update(model=str(args.model), data=str(args.data), file_bytes=size, gaussians=count)
    if aligned:
        summary["aligned_poses"] = {name: {"rotation_deg": a.rotation_deg, "shift": a.shift,
                                           "world_to_camera": [[float(v) for v in row] for row in a.camera.world_to_camera]}
                                    for name, a in aligned.items()}
    if seams is not None:
        summary.update(worst_boundary_dip=seams["worst_dip"], seam_flicker_ratio=seams["flicker_ratio"])
        print(f"seams: worst boundary dip {seams['worst_dip']:.2f} dB (interior {seams['interior_psnr']:.2f} dB), "
              f"flicker ratio {seams['flicker_ratio']:.2f} (temporal error at the worst seam over inside "
              f"segments)", file=sys.stderr)
    print(json.dumps(summary))
    if args.json:
        from stg_runtime.atomic import write_atomic

        write_atomic(args.json, json.dumps({**summary, "per_frame": result["per_frame"], "seams": seams}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
