"""What the command lines share: the one-line-error parser and argument types (stg_runtime.arguments),
the dataset options, the figures table. Imports nothing heavy: `--help` answers at once."""
from __future__ import annotations

import argparse

from stg_runtime.arguments import (Parser, error, finite_float, given_options, image_size,  # noqa: F401 (shared)
                                   nonnegative_int, port, positive_float, positive_int)


def add_dataset_options(p: argparse.ArgumentParser, depth_bounds: bool = False) -> None:
    """--layout, --fps, --test-camera, --downscale, --frames and --from-video: how DATA is read; with depth_bounds
    also --near and --far (check them with check_dataset_options)."""
    from ..choices import LAYOUTS

    p.add_argument("--layout", choices=("auto",) + LAYOUTS, default="auto",
                   help="dataset layout of DATA (default auto: detected from its files)")
    p.add_argument("--fps", type=positive_float, default=None, metavar="FPS",
                   help="frame rate of the data (default: the videos', else 30 for layouts that store none)")
    p.add_argument("--test-camera", default=None, metavar="NAME",
                   help="camera held out for evaluation (default: cam00 for n3v and reference, cam10 for "
                        "technicolor, the centre camera (camera_0001) for immersive, the first camera by name for rig)")
    p.add_argument("--downscale", type=positive_int, default=1, metavar="K",
                   help="divide the frames' width and height by K (default 1; stg-eval takes the K used in training)")
    p.add_argument("--frames", type=positive_int, default=None, metavar="N",
                   help="use only the first N frames of every camera (default: all; needed where the cameras' "
                        "frame counts differ)")
    p.add_argument("--from-video", action="store_true",
                   help="decode the videos even where lossless PNG frames exist (n3v: camXX.mp4 over "
                        "frames/camXX/*.png; immersive: camera_NNNN.mp4 over camera_NNNN/; rig: videos/ over images/)")
    if depth_bounds:
        p.add_argument("--near", type=positive_float, default=None, metavar="DEPTH",
                       help="nearest depth of the scene from every camera, in world units (with --far): the "
                            "bounds of the view-volume initialisation and of guided sampling, replacing the "
                            "layout's (default: N3V's poses_bounds.npy, else from the COLMAP model's 3D points, "
                            "else from the SfM points)")
        p.add_argument("--far", type=positive_float, default=None, metavar="DEPTH",
                       help="farthest depth of the scene from every camera, in world units (with --near)")


def check_dataset_options(parser: argparse.ArgumentParser, args) -> None:
    """parser.error (exit code 2) for --near without --far (or the other way round) or far <= near."""
    near, far = getattr(args, "near", None), getattr(args, "far", None)
    if (near is None) != (far is None):
        parser.error(f"{'--near' if far is None else '--far'} needs {'--far' if far is None else '--near'}: give "
                     "both depth bounds (world units)")
    if near is not None and not far > near:
        parser.error(f"--far {far:g} must be larger than --near {near:g}")


def dataset_options(args) -> dict:
    """The keyword arguments of stg_train.data.load_dataset from add_dataset_options' arguments (and
    --quiet)."""
    options = dict(layout=args.layout, downscale=args.downscale, from_video=args.from_video, fps=args.fps,
                   test_camera=args.test_camera, show_progress=not args.quiet, num_frames=args.frames)
    if getattr(args, "near", None) is not None:
        options["depth_range"] = (args.near, args.far)
    return options


def format_table(figures: dict, file_bytes: int, gaussians: int | None = None) -> str:
    """The held-out figures (stg_train.metrics.HELDOUT_KEYS, the dynamic / static REGION_KEYS and LPIPS
    where computed), size and Gaussian count, one per line."""
    rows = [("PSNR (dB)", f"{figures['psnr']:.2f}")]
    if figures.get("aligned_psnr") is not None:
        rows.append(("PSNR colour-aligned (dB)", f"{figures['aligned_psnr']:.2f}"))
    rows += [("SSIM", f"{figures['ssim']:.4f}"),
            ("DSSIM1", f"{figures['dssim1']:.4f}"), ("DSSIM2", f"{figures['dssim2']:.4f}"),
            ("render FPS", f"{figures['fps']:.1f}"), ("model size (MB)", f"{file_bytes / 1e6:.2f}")]
    if figures.get("dynamic_fraction") is not None:
        def pair(key, fmt):
            return " / ".join("-" if figures.get(f"{r}_{key}") is None else format(figures[f"{r}_{key}"], fmt)
                              for r in ("dynamic", "static"))
        rows += [("PSNR dynamic / static (dB)", pair("psnr", ".2f")), ("SSIM dynamic / static", pair("ssim", ".4f")),
                 ("dynamic pixels", f"{100 * figures['dynamic_fraction']:.1f}% (ground truth changes by more "
                                    f"than {figures['dynamic_threshold']:g})")]
    for key, label in (("lpips_alex", "LPIPS (AlexNet)"), ("lpips_vgg", "LPIPS (VGG)")):
        if key in figures:
            rows.append((label, f"{figures[key]:.4f}"))
    if gaussians is not None:
        rows.append(("Gaussians", str(gaussians)))
    rows.append(("images", f"{figures['images']} ({', '.join(figures['cameras'])})"))
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"{k:<{width}}  {v}" for k, v in rows)
