"""`stg-render`: render a video of a `.stg` model from a training camera, an orbit or a camera-path file."""
from __future__ import annotations

import argparse
import sys
import warnings

from .arguments import Parser, error, finite_float, image_size, nonnegative_int, positive_float

PROG = "stg-render"

EPILOG = """examples:
  stg-render --demo --out demo.mp4                  the built-in demo scene, orbiting camera
  stg-render scene.stg --out cam3.mp4 --camera 3    training camera 3, every frame of the model
  stg-render scene.stg --out frames/ --orbit --size 640x360 --start 1 --end 2
  stg-render scene.stg --out path.mp4 --path cameras.json   one camera per output frame

--out: .mp4, .mov, .mkv (H.264, yuv420p: plays in every browser), .webm (VP9) or .gif write a video
(needs PyAV: python -m pip install av); a name without a suffix, or ending in /, receives PNG frames.
H.264 and VP9 need even sizes: an odd width or height is cropped by one pixel, with a note.

Times: frame k of the output shows the model at --start + k / --fps seconds, up to --end.
--path JSON: one camera per output frame (docs/render.md has the file's schema and an example): the
video has as many frames as the path has cameras, frame k seen from camera k at --start + k / --fps; a
path longer than the model's time span (from --start to --end) is refused, a shorter one ends early
(the run says which times it renders); a path of one camera is a fixed view over the whole span.
Exit codes: 0 done, 2 bad arguments, model or camera path."""


def build_parser() -> Parser:
    p = Parser(prog=PROG, description=__doc__.split(":", 1)[1].strip(), epilog=EPILOG,
               formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("model", nargs="?", help="the .stg model to play (omit with --demo)")
    p.add_argument("--out", required=True,
                   help="output video (.mp4, .mov, .mkv, .webm, .gif) or folder for PNG frames (no suffix, or ending in /)")
    view = p.add_mutually_exclusive_group()
    view.add_argument("--camera", type=nonnegative_int, metavar="N", help="render from training camera N (default 0)")
    view.add_argument("--orbit", action="store_true", help="a circular path around the training rig")
    view.add_argument("--path", metavar="JSON",
                      help="a camera-path file: a JSON list of camera objects, one per output frame (docs/render.md)")
    p.add_argument("--size", type=image_size, metavar="WxH", help="output size (default: the camera's)")
    p.add_argument("--start", type=finite_float, help="first time in seconds (default: the model's start)")
    p.add_argument("--end", type=finite_float,
                   help="last time in seconds, inclusive (default: the model's last frame)")
    p.add_argument("--fps", type=positive_float, help="frames per second of the output (default: the model's)")
    p.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda"], help="where to render (default auto)")
    p.add_argument("--demo", action="store_true", help="play the built-in procedural demo model instead of MODEL")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.model is not None and args.demo:
        parser.error(f"give a MODEL file or --demo, not both (got {args.model!r} and --demo)")
    if args.model is None and not args.demo:
        parser.error("give a MODEL file (or --demo)")
    from .video import output_kind

    try:
        output_kind(args.out)
    except ValueError as e:
        return error(PROG, f"--out {e}")
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            count = _render(args)
            notes = [w for w in caught if w.category.__name__ == "VideoSizeWarning"]
    except _Refused as e:
        return error(PROG, str(e))
    for w in notes:
        print(f"{PROG}: note: {w.message}", file=sys.stderr)
    print(f"wrote {count} frames to {args.out}")
    return 0


class _Refused(Exception):
    """Bad input found after parsing: the message names the option or file."""


def _player(args):
    from .format import FormatError
    from .player import Player

    if args.demo:
        from .demo import demo_model
        source = demo_model("full")
    else:
        source = args.model
    try:
        return Player(source, device=args.device)
    except FormatError as e:
        raise _Refused(str(e)) from None
    except IsADirectoryError:
        raise _Refused(f"{args.model}: is a folder, not a .stg model") from None
    except OSError as e:
        raise _Refused(f"{args.model}: {e.strerror or e}") from None
    except (RuntimeError, ValueError) as e:  # --device cuda without a GPU
        raise _Refused(f"--device {args.device}: {e}") from None


def _times(args, player):
    """(start, end, fps, times): the output's frame times in seconds (see the epilog)."""
    import numpy as np

    fps = args.fps or player.fps
    first, last = player.start_time, player.start_time + player.duration - 1.0 / player.fps
    start = first if args.start is None else args.start
    end = last if args.end is None else args.end
    span = f"the model plays {first:g}..{last:g} s"
    if not first - 1e-9 <= start <= last + 1e-9:
        raise _Refused(f"--start {start:g}: outside the model's time span ({span})")
    if not first - 1e-9 <= end <= player.start_time + player.duration + 1e-9:
        raise _Refused(f"--end {end:g}: outside the model's time span ({span})")
    if end < start:
        raise _Refused(f"--end {end:g} is before --start {start:g}")
    times = start + np.arange(int(np.floor((end - start) * fps + 1e-6)) + 1) / fps
    return start, end, fps, times


def _cameras(args, player, times, fps: float):
    """(cameras, times): one camera per output frame, or one fixed camera."""
    from .camera import load_camera_path, orbit

    size = args.size
    if args.path:
        cameras = load_camera_path_or_refuse(args.path, load_camera_path)
        if size:
            cameras = [c.resized(*size) for c in cameras]
        if len(cameras) > 1:
            if len(cameras) > len(times):
                raise _Refused(f"--path {args.path}: {len(cameras)} cameras, one per frame, need "
                               f"{len(cameras)} frames at {fps:g} fps, "
                               f"but the model's time from {times[0]:g} to {times[-1]:g} s has {len(times)}: give at "
                               f"most {len(times)} cameras, or a higher --fps")
            if len(cameras) < len(times) and not args.quiet:
                print(f"{PROG}: --path {args.path}: {len(cameras)} cameras: rendering t = {times[0]:g}..."
                      f"{times[len(cameras) - 1]:g} s, one camera per frame", file=sys.stderr)
            times = times[: len(cameras)]
        sizes = {(c.width, c.height) for c in cameras}
        if len(sizes) > 1:
            raise _Refused(f"--path {args.path}: the cameras have different sizes {sorted(sizes)}; a video has one "
                           "(give --size WxH to render them all at one)")
        return cameras, times
    if not player.cameras:
        raise _Refused(f"{args.model or 'the demo model'}: stores no training cameras: give --path JSON")
    if args.orbit:
        return orbit(player.cameras, len(times), width=size[0] if size else None,
                     height=size[1] if size else None), times
    index = args.camera or 0
    if index >= len(player.cameras):
        raise _Refused(f"--camera {index}: the model has {len(player.cameras)} cameras (0..{len(player.cameras) - 1})")
    cam = player.cameras[index]
    return [cam.resized(*size) if size else cam], times


def load_camera_path_or_refuse(path, load):
    try:
        return load(path)
    except ValueError as e:
        raise _Refused(f"--path {e}") from None


def _render(args) -> int:
    from .player import RenderError

    if args.device == "cuda":
        from .cuda.device import usable

        if not usable():
            raise _Refused("--device cuda: numba sees no CUDA GPU here: use --device cpu (or auto)")
    if args.path:  # a bad path file is reported before the model is loaded
        from .camera import load_camera_path
        load_camera_path_or_refuse(args.path, load_camera_path)
    player = _player(args)
    _, _, fps, times = _times(args, player)
    cameras, times = _cameras(args, player, times, fps)
    try:
        return player.render_video(args.out, cameras, times=times, fps=fps, progress=not args.quiet)
    except RenderError as e:
        raise _Refused(str(e)) from None
    except (OSError, ValueError, RuntimeError) as e:
        raise _Refused(f"--out {args.out}: {getattr(e, 'strerror', None) or e}") from None


if __name__ == "__main__":
    sys.exit(main())
