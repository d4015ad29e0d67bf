"""`stg-render`: render a video of a `.stg` model from a training camera, an orbit or a camera-path file."""
from __future__ import annotations

import argparse
import sys

import numpy as np

from .camera import load_camera_path, orbit
from .format import FormatError
from .player import Player

EPILOG = """examples:
  stg-render --demo --out demo.mp4                  the built-in demo scene, orbiting camera
  stg-render scene.stg --out cam3.mp4 --camera 3    training camera 3, every frame of the model
  stg-render scene.stg --out frames/ --orbit --size 640x360 --start 1 --end 2
  stg-render scene.stg --out path.mp4 --path cameras.json   one camera per output frame

A folder (any --out without a video suffix) receives PNG frames; .mp4/.avi/.mov/.mkv need OpenCV."""


def parse_size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
        if w > 0 and h > 0:
            return w, h
    except ValueError:
        pass
    raise argparse.ArgumentTypeError(f"size must look like 640x360, got {text!r}")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="stg-render", description=__doc__.split(":", 1)[1].strip(),
                                epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("model", nargs="?", help="the .stg model to play (omit with --demo)")
    p.add_argument("--out", required=True, help="output video file (.mp4, ...) or folder for PNG frames")
    view = p.add_mutually_exclusive_group()
    view.add_argument("--camera", type=int, metavar="N", help="render from training camera N (default 0)")
    view.add_argument("--orbit", action="store_true", help="a circular path around the training rig")
    view.add_argument("--path", metavar="JSON", help="a camera-path file: a list of camera objects, one per frame")
    p.add_argument("--size", type=parse_size, metavar="WxH", help="output size (default: the camera's)")
    p.add_argument("--start", type=float, help="first time in seconds (default: the model's start)")
    p.add_argument("--end", type=float, help="last time in seconds, inclusive (default: the model's end)")
    p.add_argument("--fps", type=float, help="frames per second of the output (default: the model's)")
    p.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda"], help="where to render (default auto)")
    p.add_argument("--demo", action="store_true", help="play the built-in procedural demo model instead of MODEL")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if (args.model is None) == (not args.demo):
        parser.error("give a MODEL file or --demo (not both)")
    try:
        if args.demo:
            from .demo import demo_model
            source = demo_model("full")
        else:
            source = args.model
        player = Player(source, device=args.device)
        fps = args.fps or player.fps
        start = player.start_time if args.start is None else args.start
        end = player.start_time + player.duration if args.end is None else args.end
        if args.end is None:  # the model's last frame, not the instant after it
            end -= 1.0 / player.fps
        if end < start:
            parser.error(f"--end ({end}) is before --start ({start})")
        times = start + np.arange(int(np.floor((end - start) * fps + 1e-6)) + 1) / fps
        if args.path:
            cameras = load_camera_path(args.path)
            if args.size:
                cameras = [c.resized(*args.size) for c in cameras]
            times = times[: len(cameras)] if len(cameras) < len(times) else times
            cameras = cameras[: len(times)]
        elif not player.cameras:
            parser.error("the model has no training cameras: use --path")
        elif args.orbit:
            cameras = orbit(player.cameras, len(times), width=args.size[0] if args.size else None,
                            height=args.size[1] if args.size else None)
        else:
            index = args.camera or 0
            if not 0 <= index < len(player.cameras):
                parser.error(f"--camera {index}: the model has {len(player.cameras)} cameras (0..{len(player.cameras) - 1})")
            cam = player.cameras[index]
            cameras = [cam.resized(*args.size) if args.size else cam]
        count = player.render_video(args.out, cameras, times=times, fps=fps, progress=not args.quiet)
    except (FormatError, ValueError, RuntimeError, OSError) as e:
        print(f"stg-render: error: {e}", file=sys.stderr)
        return 2
    print(f"wrote {count} frames to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
