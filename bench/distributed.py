#!/usr/bin/env python
"""Segments per hour with 1 and 2 parallel workers on a small synthetic scene: a local Ray with W CPUs
runs one segment task per CPU (`stg-train --ray` with --threads 1), and, with --device cuda, one task per
GPU (`--gpus`, one worker process per GPU) where this machine has that many NVIDIA GPUs.

    python bench/distributed.py [--segments 4] [--segment-frames 4] [--iterations 30] [--workers 1,2]
                                [--device cpu|cuda] [--data DIR]

The scene (4 cameras at 64x48, segments x segment-frames frames) is written once into --data. Each
configuration trains every segment afresh into its own temporary OUT, merges and evaluates; the time
counted is the whole run (Ray's start included, printed apart) and the figure is segments / hours. A
sequential run in this process (--threads 1) is the reference. On a machine with few cores shared with
other work, parallel CPU workers compete for the same cores: read the ratio, not the absolute figure.
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import stg_train  # noqa: F401  (first: it configures OpenMP before torch loads)
import torch

from stg_train.data import load_dataset
from stg_train.pipeline import train_segments
from stg_train.synthetic import SyntheticScene, write_n3v
from stg_train.trainer import TrainConfig


def scene(data: Path, frames: int) -> Path:
    if not (data / "poses_bounds.npy").exists():
        write_n3v(data, SyntheticScene(seed=0, duration=frames / 4.0), num_cameras=4, num_frames=frames, fps=4.0,
                  width=64, height=48)
    return data


def timed(label: str, segments: int, run) -> float:
    start = time.perf_counter()
    extra = run() or 0.0
    seconds = time.perf_counter() - start
    rate = segments / (seconds / 3600)
    print(f"{label:34s} {seconds:7.1f} s  {rate:7.1f} segments/hour" + (f"  (Ray start {extra:.1f} s)" if extra else ""),
          flush=True)
    return rate


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--segments", type=int, default=4)
    ap.add_argument("--segment-frames", type=int, default=4)
    ap.add_argument("--iterations", type=int, default=30)
    ap.add_argument("--workers", default="1,2")
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--data", default=os.path.join(tempfile.gettempdir(), "stg-bench-distributed"))
    args = ap.parse_args()
    workers = [int(w) for w in args.workers.split(",")]
    data = scene(Path(args.data) / f"f{args.segments * args.segment_frames}", args.segments * args.segment_frames)
    config = TrainConfig(iterations=args.iterations, num_points=200, init="volume", checkpoint_every=10,
                         device=args.device)
    print(f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, torch {torch.__version__}; "
          f"{args.segments} segments of {args.segment_frames} frames, 4 cameras 64x48, {args.iterations} "
          f"iterations, device {args.device}", flush=True)
    root = Path(tempfile.mkdtemp(prefix="stg-bench-distributed-"))

    def fresh():
        return load_dataset(data, lazy=True)

    rates = {}
    if args.device == "cpu":
        torch.set_num_threads(1)
        rates["sequential"] = timed("sequential, 1 thread", args.segments, lambda: not train_segments(
            fresh(), root / "seq", config, args.segment_frames, quiet=True))
        import ray

        from stg_train.distributed.ray_cluster import train_on_ray
        for w in workers:
            def run(w=w):
                t0 = time.perf_counter()
                ray.init(num_cpus=w, include_dashboard=False, log_to_driver=False, logging_level="ERROR")
                started = time.perf_counter() - t0
                try:
                    train_on_ray(fresh(), root / f"ray{w}", config, args.segment_frames, quiet=True, threads=1)
                finally:
                    ray.shutdown()
                return started
            rates[w] = timed(f"Ray, {w} worker{'s' if w > 1 else ''} x 1 CPU", args.segments, run)
    else:
        gpus = torch.cuda.device_count()
        if gpus == 0:
            sys.exit("bench/distributed.py --device cuda: torch sees no CUDA GPU here; nothing measured")
        from stg_train.distributed.local import train_on_devices
        for w in workers:
            if w > gpus:
                print(f"{w} GPU workers: not measured, this machine has {gpus} GPU{'s' if gpus > 1 else ''}")
                continue
            rates[w] = timed(f"--gpus, {w} GPU worker{'s' if w > 1 else ''}", args.segments, lambda w=w: not train_on_devices(
                fresh(), root / f"gpu{w}", config, args.segment_frames, [str(i) for i in range(w)], quiet=True))
    if 1 in rates and 2 in rates:
        print(f"speed-up of 2 workers over 1: {rates[2] / rates[1]:.2f}x")


if __name__ == "__main__":
    main()
