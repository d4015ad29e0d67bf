#!/usr/bin/env python
"""Seams of long videos: a synthetic clip trained as consecutive independent segments,
played by the runtime Player, scored frame by frame against the lossless ground truth.

    python bench/seams.py [--frames 60] [--segment-frames 30] [--iterations 1500] [--points 8000]
                          [--width 160] [--height 120] [--seed 0] [--set KEY=VALUE] [--crossfades B,...]
                          [--one-frame] [--offset O] [--reverse] [--windows] [--json PATH]

Views: the held-out camera cam00 and the two novel rig views of stg_train.synthetic.novel_view_dataset.
Prints, over those views:
- each frame's PSNR (the mean of the views' PSNRs, dB), the interior mean and each boundary frame
  (a segment's first and last frames), and the worst dip (interior mean minus the lowest boundary frame);
- the temporal error of consecutive frames, mean |(R[j+1] - R[j]) - (G[j+1] - G[j])|, at each seam
  against the pairs inside a segment, and their ratio (the flicker at a seam);
- with --one-frame: at the first, middle and last frames of segment 0, the held-out camera's dynamic
  pixels (stg_train.metrics.dynamic_mask over the clip) against a model trained on that frame alone
  (bench/ablation.py's per-frame reference): how far behind the segment's model is there.
A clip of one segment (--frames 30 --segment-frames 30) has no seam: it prints its first and last
frames against its interior, the ends of a video.

--windows measures a segment's ends without the scene's own frame-to-frame difficulty: it trains two
windows of --segment-frames frames alone (no context, as a video's ends), A from frame 0 and B half a
window later, and prints, frame by frame where they overlap, B's PSNR minus A's: negative at B's first
frames (its edge, A's interior) and positive at A's last frames (A's edge, B's interior). The clip needs
1.5 windows of frames:

    python bench/seams.py --windows --frames 45 --segment-frames 30 --iterations 1500

--reverse plays the clip backwards (its last frame first, for training and scoring): a dip that stays
with the scene's frame is the scene's, one that moves to the new first or last frame is the method's.

--offset O trains and scores the scene's frames O .. O + frames - 1 instead of 0 .. frames - 1 (the
same scene: its motion and its fader's timing are those of the clip of --frames frames, continued
before and after it; SyntheticScene's start), so its seams and ends fall O frames later in the scene
(earlier when O is negative). Frame j of the output is the scene's frame O + j. A seam frame's, or a
video's end frame's, PSNR against the same scene frame's in an --offset run, where it lies inside a
segment, is what the seam or the end costs there, free of how hard that frame of the scene is:

    python bench/seams.py --frames 150 --segment-frames 50 --iterations 3000 --offset 25
    python bench/seams.py --frames 60 --segment-frames 30 --iterations 1500 --offset -15   # frame 0 inside

The figures are stg_train.metrics.evaluate_seams over the views' evaluate_player rows; the clip is the demo scene's (stg_train.synthetic),
written once per size into a temp folder (or --data). Training settings are the defaults of
stg-train (TrainConfig) with --iterations and --points; --set KEY=VALUE changes a TrainConfig field
(VALUE as JSON, else a string), to compare a method against the baseline (`--set segment_context=0`:
hard cuts, as before format 1.3); --crossfades also plays the same segments merged with other
crossfade widths (stg_train.convert.merge.merge_models).
"""
from __future__ import annotations

import argparse
import copy
import json
import os
import sys
import tempfile
from pathlib import Path

import stg_train  # noqa: F401  (first: it configures OpenMP before torch loads)
import numpy as np

from stg_runtime.format import load
from stg_runtime.player import Player
from stg_train.convert.merge import merge_models
from stg_train.config import TrainConfig
from stg_train.data import load_n3v
from stg_train.metrics import evaluate_player, evaluate_seams
from stg_train.pipeline import DEMO_SCENE, ensure_demo_scene, train
from stg_train.synthetic import SyntheticScene, novel_view_dataset

sys.path.insert(0, str(Path(__file__).parent))
from ablation import frame_figures, parse_setting, per_frame_reference  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--segment-frames", type=int, default=30)
    ap.add_argument("--iterations", type=int, default=1500, help="training steps per segment")
    ap.add_argument("--points", type=int, default=8000)
    ap.add_argument("--width", type=int, default=160)
    ap.add_argument("--height", type=int, default=120)
    ap.add_argument("--seed", type=int, default=0, help="training seed")
    ap.add_argument("--set", type=parse_setting, action="append", default=[], metavar="KEY=VALUE",
                    help="a TrainConfig field (VALUE as JSON, else a string)")
    ap.add_argument("--crossfades", type=lambda v: [int(x) for x in v.split(",") if x], default=[],
                    metavar="B,...", help="also evaluate the segments merged with these crossfade_frames "
                                          "(each at most what the segments' context allows; 0: a hard cut)")
    ap.add_argument("--one-frame", action="store_true",
                    help="also train one-frame references at segment 0's first, middle and last frames")
    ap.add_argument("--data", default=None, help="scene folder (written once; default: a temp folder per size)")
    ap.add_argument("--out", default=None, help="training folder (default: a new temp folder)")
    ap.add_argument("--json", default=None, help="also write the figures as JSON here")
    ap.add_argument("--reverse", action="store_true", help="play the clip backwards (see above)")
    ap.add_argument("--offset", type=int, default=0, metavar="O",
                    help="train and score the scene's frames O .. O + frames - 1 (see above)")
    ap.add_argument("--windows", action="store_true",
                    help="instead: two windows of --segment-frames frames half a window apart, each trained "
                         "alone; their difference where they overlap (see above)")
    args = ap.parse_args()

    size = f"12x{args.frames}" + (f"@{args.offset:+d}" if args.offset else "") + f"-{args.width}x{args.height}"
    data = Path(args.data or os.path.join(tempfile.gettempdir(), f"stg-seams-scene-{size}"))
    fps = DEMO_SCENE["fps"]
    duration, start = args.frames / fps, args.offset / fps
    ensure_demo_scene(data, frames=args.frames, width=args.width, height=args.height, duration=duration,
                      start=start)
    ds = load_n3v(data, prefer_png=True)
    scene = SyntheticScene(seed=0, duration=duration, start=start)
    novel = novel_view_dataset(scene, args.frames, ds.fps, args.width, args.height)
    if args.reverse:
        ds, novel = (reframed(d, slice(None, None, -1)) for d in (ds, novel))
    config = TrainConfig(iterations=args.iterations, num_points=args.points, seed=args.seed, **dict(args.set))
    out = Path(args.out or tempfile.mkdtemp(prefix="stg-seams-"))
    print(f"{ds}; segments of {args.segment_frames} frames, {args.iterations} steps each, {args.points} initial "
          f"points, seed {args.seed}, settings {dict(args.set)}; training into {out}", flush=True)
    if args.windows:
        figures = edge_windows(ds, novel, config, args.segment_frames, out)
        if args.json:
            Path(args.json).write_text(json.dumps({"settings": {**vars(args), "set": dict(args.set)}, **figures},
                                                  indent=1) + "\n")
        return
    train(ds, out, config, quiet=True, segment_frames=args.segment_frames)
    player = Player(out / "model.stg", device="cpu")
    rows, figures = seam_report(player, ds, novel, "as trained")
    by_crossfade = {}
    for fade in args.crossfades:
        segments = [load(f) for f in sorted((out / "segments").glob("*/model.stg"))]
        merged = Player(merge_models(segments, crossfade=fade), device="cpu")
        by_crossfade[fade] = seam_report(merged, ds, novel, f"crossfade {fade} (at most the context allows)")[1]
    one_frame = {}
    if args.one_frame:
        first = player.model.segments[0]
        cam = ds.cameras[ds.test_cameras[0]]
        for j in (first.start_frame, first.start_frame + first.num_frames // 2,
                  first.start_frame + first.num_frames - 1):
            ref = per_frame_reference(ds, ds, config, j)
            got = frame_figures(player.render_frame(cam, j), ds, j)
            one_frame[j] = {"one_frame": ref, "segment": got}
            print(f"frame {j}: dynamic pixels {got['dynamic_psnr']:.2f} dB, one-frame model "
                  f"{ref['dynamic_psnr']:.2f} dB: {ref['dynamic_psnr'] - got['dynamic_psnr']:.2f} behind", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps({"settings": {**vars(args), "set": dict(args.set)},
                                               "per_frame": rows, "figures": figures, "one_frame": one_frame,
                                               "by_crossfade": by_crossfade}, indent=1) + "\n")


def reframed(dataset, frames: slice):
    """A copy of `dataset` whose frame j is the original's frames[j] (a slice: slice(None, None, -1)
    plays it backwards): a clip of its own, whose time starts at its frame 0."""
    clip = copy.copy(dataset)
    clip.frames = np.ascontiguousarray(np.asarray(dataset.frames)[:, frames])
    return clip


def edge_windows(ds, novel, config: TrainConfig, window: int, out: Path) -> dict:
    """Windows A (frames [0, window)) and B ([window // 2, window // 2 + window)) of `ds`, each trained
    alone into out/A, out/B. Prints B - A where they overlap; returns {"offset": window // 2,
    "per_frame": {"psnr" | "dynamic_psnr": {"A" | "B": {clip frame: dB}}}}, each frame's PSNR (over all
    pixels, or the dynamic ones) the mean over the held-out camera and the novel views."""
    offset = window // 2
    if ds.num_frames < offset + window:
        raise SystemExit(f"--windows needs at least {offset + window} frames (--frames), got {ds.num_frames}")
    per_frame = {"psnr": {}, "dynamic_psnr": {}}
    for name, start in (("A", 0), ("B", offset)):
        train(ds.frame_range(start, window), out / name, config, quiet=True)
        player = Player(out / name / "model.stg", device="cpu")
        rows = [r for views in (ds, novel) for r in evaluate_player(player, views.frame_range(start, window))["per_frame"]]
        for key in per_frame:  # rows count frames from the window's start
            per_frame[key][name] = {start + j: float(np.nanmean([np.nan if r[key] is None else r[key]
                                                                 for r in rows if r["frame"] == j]))
                                    for j in range(window)}
    both = range(offset, window)
    for key, label in (("psnr", "all pixels"), ("dynamic_psnr", "dynamic pixels")):
        a, b = per_frame[key]["A"], per_frame[key]["B"]
        print(f"B - A ({label}), frames {both.start}-{both.stop - 1} (B's first .. A's last): "
              + " ".join(f"{b[j] - a[j]:+.2f}" for j in both), flush=True)
    return {"offset": offset, "per_frame": per_frame}


def seam_report(player, ds, novel, label: str):
    """(per-frame rows, evaluate_seams figures) of `player` over the held-out camera and the novel
    views, printed under `label`."""
    rows = evaluate_player(player, ds)["per_frame"] + evaluate_player(player, novel)["per_frame"]
    figures = evaluate_seams({"per_frame": rows}, [s.start_frame for s in player.model.segments], require_seam=False)
    fades = [s.crossfade_frames for s in player.model.segments[1:]]
    print(f"{label} (crossfades {fades}): interior mean {figures['interior_psnr']:.2f} dB; boundary frames: "
          + ", ".join(f"{f}: {p:.2f} dB ({p - figures['interior_psnr']:+.2f})" for f, p in figures["boundary"].items()))
    print(f"  worst dip {figures['worst_dip']:.2f} dB; temporal error inside segments "
          f"{figures['interior_pair_error']:.4f}; at the seams: " + (", ".join(
              f"{s - 1}->{s}: {e:.4f} ({e / figures['interior_pair_error']:.2f}x)" for s, e in figures["seams"].items())
              or "none (one segment)"), flush=True)
    return rows, figures


if __name__ == "__main__":
    main()
