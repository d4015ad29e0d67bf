"""`stg-synth`: write a synthetic dynamic scene in the Neural 3D Video layout, or through a dome of fisheye
(or pinhole) cameras in the Google Immersive layout (see stg_train.synthetic)."""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

from .common import Parser, error, image_size, positive_float, positive_int


def _size(text: str) -> tuple[int, int]:
    return image_size(text, minimum=8)


def _fov(limit: float):
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a field of view in degrees, got {text!r}") from None
        if not 0 < value < limit:
            raise argparse.ArgumentTypeError(f"the field of view must be above 0 and below {limit:g} degrees, got {text}")
        return value
    return parse


def build_parser() -> argparse.ArgumentParser:
    p = Parser(
        prog="stg-synth",
        description="Ray trace a small dynamic scene (a textured room with a moving sphere, a spinning box, "
                    "an object that fades in and out and a specular highlight) seen by a forward-facing "
                    "camera rig, and write it in the Neural 3D Video layout: camXX.mp4 per camera, "
                    "poses_bounds.npy (LLFF convention), lossless frames/camXX/NNNNNN.png and scene.json. "
                    "cam00 is the centre camera, held out for testing. With --fisheye HFOV (or --pinhole-dome "
                    "HFOV) the scene is seen by an outward-facing dome of equidistant fisheye (or pinhole) "
                    "cameras instead and written in the Google Immersive layout: camera_NNNN.mp4 per camera, "
                    "models.json, lossless camera_NNNN/NNNNNN.png and scene.json; camera_0001, the centre "
                    "camera, is held out.")
    p.add_argument("out_dir", help="output folder (created if missing; existing files are overwritten)")
    p.add_argument("--cameras", type=positive_int, default=12, metavar="N",
                   help="number of cameras in the rig (default 12)")
    p.add_argument("--frames", type=positive_int, default=30, metavar="N",
                   help="number of frames per camera (default 30)")
    p.add_argument("--fps", type=positive_float, default=30.0,
                   help="frames per second; frame k shows time k / fps seconds (default 30)")
    p.add_argument("--size", type=_size, default=(160, 120), metavar="WxH",
                   help="image width x height in pixels (default 160x120)")
    p.add_argument("--focal", type=positive_float, default=None, metavar="PIXELS",
                   help="focal length in pixels (default 0.9 x width)")
    dome = p.add_mutually_exclusive_group()
    dome.add_argument("--fisheye", type=_fov(360.0), default=None, metavar="HFOV",
                      help="an outward-facing dome of equidistant fisheye cameras (OpenCV fisheye model, k1..k4 "
                           "= 0) of horizontal field of view HFOV degrees (below 360), in the Immersive layout")
    dome.add_argument("--pinhole-dome", type=_fov(180.0), default=None, metavar="HFOV",
                      help="the same dome with pinhole cameras of horizontal field of view HFOV degrees (below "
                           "180), in the Immersive layout: the pinhole rig of similar coverage to compare with")
    p.add_argument("--seed", type=int, default=0, help="seed of the procedural textures and colours (default 0)")
    p.add_argument("--supersample", type=positive_int, default=1, metavar="S",
                   help="S x S rays per pixel, averaged, against aliasing (default 1; time grows as S^2)")
    p.add_argument("--no-png", action="store_true",
                   help="do not write the lossless PNG frames (only the mp4 videos)")
    p.add_argument("--quiet", action="store_true", help="no progress line")
    _add_capture_options(p)
    return p


#: --realistic's knobs: option -> (CaptureModel field, metavar, help)
CAPTURE_KNOBS = {
    "--gain": ("gain", "STOPS", "standard deviation of each camera's exposure, in stops"),
    "--white-balance": ("white_balance", "SD", "standard deviation of each camera's per-channel gains around 1"),
    "--vignetting": ("vignetting", "F", "brightness lost at the image corners (0.3: 30%% darker)"),
    "--noise": ("noise", "SD", "standard deviation of the sensor noise per pixel and channel, in [0, 1] units"),
    "--pose-rotation": ("rotation_deg", "DEG", "size of each camera's pose error: a rotation about a random axis"),
    "--pose-translation": ("translation", "UNITS", "size of each camera's pose error: a shift in a random "
                                                   "direction, world units"),
}


def _nonnegative_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not value >= 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"expected a finite number of at least 0, got {text}")
    return value


def _add_capture_options(p: argparse.ArgumentParser) -> None:
    from ..rig.capture import CaptureModel  # numpy only

    defaults = CaptureModel()
    group = p.add_argument_group(
        "realistic capture (N3V layout)",
        "--realistic records the frames as a real rig would (stg_train.rig.capture.CaptureModel): per-camera "
        "exposure and white balance, lens vignetting, sensor noise, and poses_bounds.npy states slightly wrong "
        "poses; scene.json keeps the truth (each camera's effects and true pose) under \"capture\". Each knob "
        "implies --realistic; 0 turns its effect off. The per-camera values are drawn from --seed.")
    group.add_argument("--realistic", action="store_true", help="a realistic capture with the knobs' defaults")
    for option, (name, metavar, text) in CAPTURE_KNOBS.items():
        group.add_argument(option, type=_nonnegative_float, default=None, metavar=metavar,
                           help=f"{text} ({getattr(defaults, name):g} when not given)")


def _capture(args):
    """The CaptureModel the arguments ask for, or None."""
    knobs = {name: getattr(args, option[2:].replace("-", "_")) for option, (name, _, _) in CAPTURE_KNOBS.items()}
    if not args.realistic and all(v is None for v in knobs.values()):
        return None
    from ..rig.capture import CaptureModel

    return CaptureModel(seed=args.seed, **{k: v for k, v in knobs.items() if v is not None})


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    hfov = args.fisheye if args.fisheye is not None else args.pinhole_dome
    if hfov is not None and args.focal is not None:
        parser.error("--focal applies to the N3V rig; the dome's focal length follows from HFOV")
    capture = _capture(args)
    if hfov is not None and capture is not None:
        parser.error("--realistic and its knobs apply to the N3V rig, not to the dome (--fisheye, --pinhole-dome)")
    if os.path.exists(args.out_dir) and not os.path.isdir(args.out_dir):
        return error("stg-synth", f"{args.out_dir}: is a file, not a folder")
    parent = next(p for p in Path(args.out_dir).absolute().parents if p.exists())
    if not parent.is_dir():
        return error("stg-synth", f"{args.out_dir}: cannot create it: {parent} is a file")
    from stg_runtime.progress import Progress

    from ..synthetic import SyntheticScene, write_immersive, write_n3v

    width, height = args.size
    scene = SyntheticScene(seed=args.seed, duration=args.frames / args.fps)
    start = time.monotonic()
    common = dict(num_cameras=args.cameras, num_frames=args.frames, fps=args.fps, width=width, height=height,
                  png=not args.no_png, supersample=args.supersample)
    try:
        with Progress(total=args.cameras * args.frames, desc="stg-synth frames", enabled=not args.quiet) as bar:
            report = lambda done, total: bar.update(done - bar.count)  # noqa: E731
            if hfov is None:
                write_n3v(args.out_dir, scene, focal=args.focal, progress=report, capture=capture, **common)
            else:
                write_immersive(args.out_dir, scene, hfov_deg=hfov, progress=report,
                                model="fisheye" if args.fisheye is not None else "pinhole", **common)
    except OSError as e:
        return error("stg-synth", f"{e.filename or args.out_dir}: {e.strerror or e}")
    if not args.quiet:
        layout = "N3V" if hfov is None else "Immersive"
        print(f"wrote {args.cameras} cameras x {args.frames} frames at {width}x{height} ({layout} layout) to {args.out_dir} "
              f"in {time.monotonic() - start:.1f} s", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
