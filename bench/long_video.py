#!/usr/bin/env python
"""Long videos: the same synthetic clip trained as consecutive segments with each schedule of
`stg-train --segment-schedule` (independent: every segment from initial points; warm: each from its
predecessor, stg_train.warm), side by side in one run.

    python bench/long_video.py [--frames 150] [--segment-frames 50] [--iterations 3000] [--points 8000]
                               [--width 160] [--height 120] [--scene-seed 0] [--layout 0] [--seed 0]
                               [--schedules independent,warm] [--set KEY=VALUE] [--threads N]
                               [--data DIR] [--out DIR] [--json PATH]

Each schedule trains in a process of its own (this script again, with --child), with TrainConfig's
defaults, --iterations, --points, --seed and the --set fields (`--set warm_fraction=0.2`). The parent
prints, per schedule:
- the whole job's wall time (training, every segment's evaluation, the merge and the final evaluation:
  what a user waits for) and its ratio to the first schedule's;
- per segment: its training seconds and steps (OUT/segments/NN/metrics.json), its PSNR (the mean over
  its frames of the views' mean PSNR, played from the merged model) and the peak resident memory of
  the training process while it ran, all of it and its anonymous part (without the memory-mapped
  frame caches), sampled every 0.2 s from /proc: whether memory grows with the number of segments;
- the seam figures of bench/seams.py (stg_train.metrics.evaluate_seams): interior mean PSNR, each
  boundary frame against it, and the temporal error at each seam against the interior's.
Views: the held-out camera cam00 and the two novel rig views (stg_train.synthetic.novel_view_dataset),
scored against the lossless frames. The clip is stg_train.synthetic's scene --scene-seed (textures and
colours) with object set --layout (0: the demo's; 1: a second scene), written once per size into a
temp folder (or --data). The 150-frame clip of docs/training.md's seams table and a 300-frame clip
of a second scene:

    python bench/long_video.py --frames 150 --segment-frames 50 --iterations 3000
    python bench/long_video.py --frames 300 --segment-frames 50 --iterations 3000 --scene-seed 1 --layout 1
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import stg_train  # noqa: F401  (first: it configures OpenMP before torch loads)
import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from ablation import parse_setting  # noqa: E402
from machine import describe  # noqa: E402

SCHEDULES = ("independent", "warm")


def main() -> None:
    args = parse_args()
    data = Path(args.data or os.path.join(
        tempfile.gettempdir(), f"stg-long-scene-{args.scene_seed}-{args.layout}-12x{args.frames}-{args.width}x{args.height}"))
    if args.child:
        train_child(args, data)
        return
    from stg_train.pipeline import DEMO_SCENE, ensure_demo_scene
    ensure_demo_scene(data, frames=args.frames, width=args.width, height=args.height,
                      duration=args.frames / DEMO_SCENE["fps"], seed=args.scene_seed, layout=args.layout)
    out = Path(args.out or tempfile.mkdtemp(prefix="stg-long-"))
    print(describe())
    print(f"clip: scene seed {args.scene_seed}, layout {args.layout}, {args.frames} frames at {args.width}x"
          f"{args.height}, segments of {args.segment_frames}; {args.iterations} steps per cold segment, "
          f"{args.points} points, seed {args.seed}, settings {dict(args.set)}; training into {out}", flush=True)
    runs = {}
    for schedule in args.schedules:
        runs[schedule] = run_schedule(args, data, out / schedule, schedule)
        runs[schedule].update(score(args, data, out / schedule))
    report(runs)
    if args.json:
        Path(args.json).write_text(json.dumps({"settings": {**vars(args), "set": dict(args.set)}, "runs": runs},
                                              indent=1, default=float) + "\n")


def parse_args():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--segment-frames", type=int, default=50)
    ap.add_argument("--iterations", type=int, default=3000, help="training steps of a cold segment")
    ap.add_argument("--points", type=int, default=8000)
    ap.add_argument("--width", type=int, default=160)
    ap.add_argument("--height", type=int, default=120)
    ap.add_argument("--scene-seed", type=int, default=0, help="the synthetic scene's seed (textures, colours)")
    ap.add_argument("--layout", type=int, default=0, help="the synthetic scene's object set (0 or 1)")
    ap.add_argument("--seed", type=int, default=0, help="training seed")
    ap.add_argument("--schedules", type=lambda v: [s for s in v.split(",") if s], default=list(SCHEDULES),
                    help="comma-separated, from independent,warm (ratios are to the first)")
    ap.add_argument("--set", type=parse_setting, action="append", default=[], metavar="KEY=VALUE",
                    help="a TrainConfig field for every schedule (VALUE as JSON, else a string)")
    ap.add_argument("--threads", type=int, default=None, help="torch threads of each training (default: all)")
    ap.add_argument("--data", default=None, help="scene folder (written once; default: a temp folder per clip)")
    ap.add_argument("--out", default=None, help="training folder (default: a new temp folder)")
    ap.add_argument("--json", default=None, help="also write the figures as JSON here")
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)  # SCHEDULE,OUT: train one schedule
    args = ap.parse_args()
    bad = [s for s in args.schedules if s not in SCHEDULES]
    if bad or not args.schedules:
        ap.error(f"--schedules: choose from {','.join(SCHEDULES)}, got {','.join(args.schedules) or 'none'}")
    return args


def train_child(args, data: Path) -> None:
    """The --child process: train `data` into OUT with one schedule (stg_train.pipeline.train)."""
    from stg_train.config import TrainConfig
    from stg_train.data import load_n3v
    from stg_train.pipeline import train
    schedule, out = args.child.split(",", 1)
    if args.threads:
        import torch
        torch.set_num_threads(args.threads)
    config = TrainConfig(iterations=args.iterations, num_points=args.points, seed=args.seed,
                         **{**dict(args.set), "segment_schedule": schedule})
    train(load_n3v(data, prefer_png=True), Path(out), config, quiet=True, segment_frames=args.segment_frames)


def run_schedule(args, data: Path, out: Path, schedule: str) -> dict:
    """Train one schedule in a child process: {"wall_seconds", "peak_rss_mb" (whole run),
    "segments": [{"index", "train_seconds", "iterations", "warm", "peak_memory_mb": {"rss", "anon"}}]}."""
    child = [sys.executable, __file__, "--child", f"{schedule},{out}", "--data", str(data)]
    for flag in ("frames", "segment_frames", "iterations", "points", "width", "height", "seed", "threads"):
        value = getattr(args, flag)
        if value is not None:
            child += [f"--{flag.replace('_', '-')}", str(value)]
    for key, value in args.set:
        child += ["--set", f"{key}={json.dumps(value)}"]
    print(f"training {schedule} ...", flush=True)
    start = time.perf_counter()
    proc = subprocess.Popen(child)
    peaks: dict[int, dict] = {}
    sampler = threading.Thread(target=sample_memory, args=(proc, out / "segments", peaks), daemon=True)
    sampler.start()
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - start
    proc.returncode = os.waitstatus_to_exitcode(status)
    sampler.join()
    if proc.returncode != 0:
        raise SystemExit(f"the {schedule} run failed (exit {proc.returncode}); its output is above")
    metrics = json.loads((out / "metrics.json").read_text())
    segments = [{"index": s["index"], "train_seconds": s["train_seconds"], "iterations": s["iterations"],
                 "warm": s["warm"], "peak_memory_mb": peaks.get(s["index"])} for s in metrics["segments"]]
    return {"wall_seconds": wall, "peak_rss_mb": usage.ru_maxrss / 1024, "segments": segments}


def sample_memory(proc, segments: Path, peaks: dict) -> None:
    """Until `proc` ends: its resident memory every 0.2 s, the largest per segment in `peaks` (the
    segment running: the count of segments/NN/metrics.json written so far) as {"rss": MB, "anon": MB}:
    all resident pages, and the anonymous ones alone (without the memory-mapped frame caches, whose
    pages the kernel can drop)."""
    status = Path(f"/proc/{proc.pid}/status")
    while proc.returncode is None:
        try:
            fields = dict(line.split(":", 1) for line in status.read_text().splitlines() if ":" in line)
            rss, anon = (int(fields[k].split()[0]) / 1024 for k in ("VmRSS", "RssAnon"))
        except (OSError, KeyError, ValueError):
            break
        running = len(list(segments.glob("*/metrics.json"))) if segments.is_dir() else 0
        peak = peaks.setdefault(running, {"rss": 0.0, "anon": 0.0})
        peak["rss"], peak["anon"] = max(peak["rss"], rss), max(peak["anon"], anon)
        time.sleep(0.2)


def score(args, data: Path, out: Path) -> dict:
    """The merged model played over cam00 and the novel views: {"per_segment_psnr": [dB], "seams":
    evaluate_seams' figures}, printed by bench/seams.py's seam_report."""
    from seams import seam_report

    from stg_runtime.player import Player
    from stg_train.data import load_n3v
    from stg_train.pipeline import DEMO_SCENE
    from stg_train.synthetic import SyntheticScene, novel_view_dataset
    ds = load_n3v(data, prefer_png=True)
    scene = SyntheticScene(seed=args.scene_seed, duration=args.frames / DEMO_SCENE["fps"], layout=args.layout)
    novel = novel_view_dataset(scene, args.frames, ds.fps, args.width, args.height)
    player = Player(out / "model.stg", device="cpu")
    rows, figures = seam_report(player, ds, novel, out.name)
    by_frame = {}
    for r in rows:
        by_frame.setdefault(r["frame"], []).append(r["psnr"])
    per_segment = []
    for s in player.model.segments:
        frames = range(s.start_frame, s.start_frame + s.num_frames)
        per_segment.append(float(np.mean([np.mean(by_frame[j]) for j in frames])))
    return {"per_segment_psnr": per_segment, "seams": figures}


def report(runs: dict) -> None:
    """The table of both schedules: wall time and its ratio, per segment seconds / PSNR / memory, seams."""
    first = next(iter(runs.values()))
    print()
    for name, run in runs.items():
        seams = run["seams"]
        interior = seams["interior_psnr"]
        worst = max((e / seams["interior_pair_error"] for e in seams["seams"].values()), default=float("nan"))
        boundary = min(p - interior for p in seams["boundary"].values())
        print(f"{name}: job {run['wall_seconds']:.0f} s ({run['wall_seconds'] / first['wall_seconds']:.2f}x), "
              f"peak memory {run['peak_rss_mb']:.0f} MB; interior {interior:.2f} dB "
              f"({interior - first['seams']['interior_psnr']:+.2f}); lowest boundary frame {boundary:+.2f} dB "
              f"against the interior; worst seam flicker {worst:.2f}x")
        for s, psnr in zip(run["segments"], run["per_segment_psnr"]):
            peak = s["peak_memory_mb"]
            peak = "-" if peak is None else f"{peak['rss']:.0f} MB ({peak['anon']:.0f} MB anonymous)"
            print(f"  segment {s['index']}: {'warm' if s['warm'] else 'cold'}, {s['iterations']} steps, "
                  f"{s['train_seconds']:.0f} s training, {psnr:.2f} dB, peak memory {peak}")


if __name__ == "__main__":
    main()
