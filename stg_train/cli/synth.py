"""`stg-synth`: write a synthetic dynamic scene in the Neural 3D Video layout (see stg_train.synthetic)."""
from __future__ import annotations

import argparse
import sys
import time

from stg_runtime.progress import Progress

from ..synthetic import SyntheticScene, write_n3v
from .common import error, positive_float, positive_int


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT, e.g. 160x120, got {text!r}") from None
    if w < 8 or h < 8:
        raise argparse.ArgumentTypeError(f"image size must be at least 8x8, got {text!r}")
    return w, h


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="stg-synth",
        description="Ray trace a small dynamic scene (a textured room with a moving sphere, a spinning box, "
                    "an object that fades in and out and a specular highlight) seen by a forward-facing "
                    "camera rig, and write it in the Neural 3D Video layout: camXX.mp4 per camera, "
                    "poses_bounds.npy (LLFF convention), lossless frames/camXX/NNNNNN.png and scene.json. "
                    "cam00 is the centre camera, held out for testing.")
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
    p.add_argument("--seed", type=int, default=0, help="seed of the procedural textures and colours (default 0)")
    p.add_argument("--supersample", type=positive_int, default=1, metavar="S",
                   help="S x S rays per pixel, averaged, against aliasing (default 1; time grows as S^2)")
    p.add_argument("--no-png", action="store_true",
                   help="do not write the lossless PNG frames (only the mp4 videos)")
    p.add_argument("--quiet", action="store_true", help="no progress line")
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    width, height = args.size
    scene = SyntheticScene(seed=args.seed, duration=args.frames / args.fps)
    start = time.monotonic()
    try:
        with Progress(total=args.cameras * args.frames, desc="stg-synth frames", enabled=not args.quiet) as bar:
            write_n3v(args.out_dir, scene, num_cameras=args.cameras, num_frames=args.frames, fps=args.fps,
                      width=width, height=height, png=not args.no_png, focal=args.focal,
                      supersample=args.supersample, progress=lambda done, total: bar.update(done - bar.count))
    except OSError as e:
        return error("stg-synth", f"{e.filename or args.out_dir}: {e.strerror or e}")
    if not args.quiet:
        print(f"wrote {args.cameras} cameras x {args.frames} frames at {width}x{height} to {args.out_dir} "
              f"in {time.monotonic() - start:.1f} s", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
