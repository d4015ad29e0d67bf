"""`stg-prep`: a folder of raw videos, one per camera, -> the rig layout that stg-train reads
(stg_train.prep)."""
from __future__ import annotations

import argparse
import sys
import time

from .common import Parser, error, positive_float, positive_int

PROG = "stg-prep"

EPILOG = """VIDEOS holds one file per camera (mp4, mov, mkv, avi, webm) or one folder of numbered frames
(png, jpg) per camera; a camera is named after its file or folder. OUT receives:

  images/<camera>/00000.png ...  the synchronised frames: frame k of every camera shows the same moment
  sparse/0/                      a COLMAP model of the rig, one image per camera
  prep.json                      the report: each camera's offset and its confidence, the frames kept,
                                 the calibration (camera model, reprojection errors), warnings, timings

Checks come first and stop with a one-line error naming the file or camera (exit code 2; OUT is left as
it was): unreadable or empty files, fewer than 2 cameras, different resolutions or frame rates, clips
too short. Clips of different lengths are cut to the span all cameras share, and the report says so.

Synchronisation: each camera's frame offset is found from its pictures (the motion energy and
brightness of every frame, cross-correlated between cameras); a low confidence is a warning naming the
camera. Calibration: pycolmap on each camera's static picture (the median of frames spread over its
clip); a camera that does not register is an error naming it with its match counts. Train the result
with `stg-train OUT --out run/` (or give stg-train VIDEOS directly: it prepares into run/prep/)."""


def _offsets(text: str):
    """'0,3,1' (one per camera, in name order) or 'cam01=3,cam02=1' (unnamed cameras 0)."""
    items = [t.strip() for t in text.split(",") if t.strip()]
    if not items:
        raise argparse.ArgumentTypeError("expected offsets such as 0,3,1 or cam01=3,cam02=1")
    named = ["=" in t for t in items]
    if any(named) and not all(named):
        raise argparse.ArgumentTypeError(f"give every offset as NAME=FRAMES or none, got {text!r}")
    try:
        if all(named):
            pairs = [t.split("=", 1) for t in items]
            values = {name.strip(): int(v) for name, v in pairs}
            if len(values) != len(pairs):
                raise argparse.ArgumentTypeError(f"a camera named twice in {text!r}")
        else:
            values = [int(t) for t in items]
    except ValueError:
        raise argparse.ArgumentTypeError(f"offsets are whole numbers of frames, got {text!r}") from None
    if any(v < 0 for v in (values.values() if isinstance(values, dict) else values)):
        raise argparse.ArgumentTypeError(f"offsets are frames to skip, 0 or more, got {text!r}")
    return values


def build_parser() -> argparse.ArgumentParser:
    from ..prep.calibrate import CAMERA_MODELS
    from ..prep.inputs import MIN_FRAMES

    p = Parser(prog=PROG, epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter,
               description="Prepare raw multi-camera videos for stg-train: check them, synchronise them, "
                           "calibrate the rig with pycolmap, and write the rig layout.")
    p.add_argument("videos", metavar="VIDEOS", help="folder of raw videos, one per camera (or frame folders)")
    p.add_argument("out", metavar="OUT", help="output folder (created; must be new or empty unless --force)")
    p.add_argument("--offsets", type=_offsets, default=None, metavar="LIST",
                   help="frame offsets by hand instead of estimating them: the frame of each camera where the "
                        "prepared video starts, as 0,3,1 (in camera-name order) or cam01=3,cam02=1 (the others "
                        "0)")
    p.add_argument("--max-offset", type=positive_int, default=None, metavar="N",
                   help="largest offset searched, in frames either way (default: a third of the shortest clip)")
    p.add_argument("--camera-model", choices=tuple(CAMERA_MODELS), default="pinhole",
                   help="lens model fitted: pinhole (one focal length; where it fits badly opencv is tried and "
                        "the report says so), opencv (radial and tangential distortion, undistorted into the "
                        "written frames), fisheye (OpenCV's fisheye model, kept in the model) (default pinhole); "
                        "each fitted once per camera and once shared by all the cameras, the shared fit kept "
                        "where it explains the features as well (identical cameras)")
    p.add_argument("--fps", type=positive_float, default=None,
                   help="frame rate of frame folders (default: the videos', else 30)")
    p.add_argument("--min-frames", type=positive_int, default=MIN_FRAMES, metavar="N",
                   help=f"shortest clip, and span common to all cameras, accepted (default {MIN_FRAMES})")
    p.add_argument("--threads", type=positive_int, default=None, metavar="N",
                   help="CPU threads of the calibration (default: all)")
    p.add_argument("--force", action="store_true", help="replace OUT if it exists and is not empty")
    p.add_argument("--quiet", action="store_true", help="no progress bars and no summary")
    return p


def summary(report: dict, out, seconds: float) -> str:
    """The lines printed after a preparation: what was written, the offsets, the calibration."""
    cal = report["calibration"]
    offsets = ", ".join(f"{c['name']} {c['offset']}" + ("" if c["confidence"] is None else f" ({c['confidence']:.2f})")
                        for c in report["cameras"])
    lines = [f"{PROG}: {len(report['cameras'])} cameras x {report['frames']} frames, {report['width']}x"
             f"{report['height']} at {report['fps']:g} fps, into {out} in {seconds:.1f} s",
             f"  offsets ({report['sync']['method']}{', confidence' if report['sync']['method'] == 'estimated' else ''}):"
             f" {offsets}",
             f"  calibration: {cal['camera_model']} ({cal['intrinsics']} intrinsics), {cal['registered']} of "
             f"{cal['cameras']} cameras registered, "
             f"mean reprojection error {cal['mean_reprojection_error_px']:.3f} px, {cal['points']} points"]
    kept = [f"{c['name']} {c['frames_used'][0]}-{c['frames_used'][1]} of {c['frames']}" for c in report["cameras"]
            if c["frames"] != report["frames"]]
    if kept:
        lines.append(f"  trimmed to the {report['frames']} frames all cameras share: {', '.join(kept)}")
    return "\n".join(lines)


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    from stg_runtime.progress import progress_stages

    from ..prep import PrepError, prepare

    start = time.perf_counter()
    try:
        with progress_stages(enabled=not args.quiet) as stage:
            report = prepare(args.videos, args.out, offsets=args.offsets, camera_model=args.camera_model,
                             fps=args.fps, max_offset=args.max_offset, min_frames=args.min_frames, force=args.force,
                             threads=args.threads or -1, progress=stage)
    except PrepError as e:
        return error(PROG, str(e))
    except OSError as e:  # a full disk, a folder that cannot be written
        return error(PROG, f"{e.filename or args.out}: {e.strerror or e}")
    for warning in report["warnings"]:
        print(f"{PROG}: warning: {warning}", file=sys.stderr)
    if not args.quiet:
        print(summary(report, args.out, time.perf_counter() - start), file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
