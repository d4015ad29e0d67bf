#!/usr/bin/env python
"""Host memory and time of training steps at the size of a real capture (the paper's Neural 3D Video
setting by default: 20 cameras at 1352x1014, 200k Gaussians), on the CPU.

    python bench/step_memory.py [--cameras 20] [--width 1352] [--height 1014] [--gaussians 200000]
                                [--steps 5] [--splatter numba|torch] [--model full|lite] [--threads 2]

The capture is made in memory: a ring of cameras around 50k random Gaussians drawn by the runtime's
splatter (two frames per camera: memory does not depend on the frame count, the frames being a
memory-mapped cache in real runs). The trainer starts from `--gaussians` view-volume points. Prints
the peak resident memory of the process before training (data and initial model), the time the
runtime's splatter takes to draw the initial Gaussians (how deep the scene is), the peak during the
steps (reset after initialisation: /proc/self/clear_refs), and the seconds per step.
"""
from __future__ import annotations

import argparse
import os
import time

import stg_train  # noqa: F401  (first: it configures OpenMP before torch loads)
import numpy as np
import torch

from stg_runtime.camera import Camera
from stg_runtime.splat_cpu import rasterize as draw
from stg_train.data.dataset import Dataset
from stg_train.trainer import Trainer, TrainConfig


def status_gb(key: str) -> float:
    """A memory figure of /proc/self/status (e.g. "VmHWM", "RssAnon"), in GB (nan when absent)."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(key + ":"):
                return int(line.split()[1]) * 1024 / 1e9
    return float("nan")


def peak_rss_gb() -> float:
    """The process's peak resident memory so far (VmHWM), in GB."""
    return status_gb("VmHWM")


def reset_peak_rss() -> None:
    """Start VmHWM again from the current resident memory (Linux)."""
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")


def capture(cameras: int, width: int, height: int, frames: int = 2, seed: int = 0) -> Dataset:
    """A ring of cameras looking at a cloud of random Gaussians, its frames drawn by the runtime."""
    rng = np.random.default_rng(seed)
    n = 50_000
    means = rng.normal(0, 1.0, (n, 3)).astype(np.float32)
    quats = rng.normal(size=(n, 4)).astype(np.float32)
    scales = np.exp(rng.uniform(np.log(0.01), np.log(0.08), (n, 3))).astype(np.float32)
    opacities = rng.uniform(0.3, 1.0, n).astype(np.float32)
    colours = rng.uniform(0, 1, (n, 3)).astype(np.float32)
    cams = []
    for i in range(cameras):
        a = 2 * np.pi * i / cameras
        eye = [4.0 * np.cos(a), 0.3 * np.sin(3 * a), 4.0 * np.sin(a)]
        cams.append(Camera.look_at(eye, [0, 0, 0], [0, -1, 0], 60.0, width, height, name=f"cam{i:02d}"))
    images = np.empty((cameras, frames, height, width, 3), np.uint8)
    for i, cam in enumerate(cams):
        for j in range(frames):
            rgb = draw(means + 0.02 * j, quats, scales, opacities, colours, cam)[0]
            images[i, j] = (np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8)
    bounds = np.tile([[1.0, 7.0]], (cameras, 1))
    return Dataset(cams, images, fps=30.0, test_cameras=[0], bounds=bounds)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cameras", type=int, default=20)
    ap.add_argument("--width", type=int, default=1352)
    ap.add_argument("--height", type=int, default=1014)
    ap.add_argument("--gaussians", type=int, default=200_000)
    ap.add_argument("--steps", type=int, default=5)
    ap.add_argument("--splatter", default="numba", choices=["numba", "torch"])
    ap.add_argument("--model", default="full", choices=["full", "lite"])
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    ds = capture(args.cameras, args.width, args.height)
    config = TrainConfig(model=args.model, num_points=args.gaussians, init="volume", depth_candidates=0,
                         splatter=args.splatter, iterations=30_000)
    trainer = Trainer(ds, config)
    print(f"{ds}; {trainer.params.count} Gaussians, {args.model} model, {args.splatter} splatter, "
          f"{args.threads} threads, {os.cpu_count()} CPUs; set-up {time.perf_counter() - t0:.0f} s, "
          f"peak memory so far {peak_rss_gb():.2f} GB", flush=True)
    trainer.train_step()  # compiles the kernels
    with torch.no_grad():  # for scale: the runtime's splatter drawing the same Gaussians
        g = trainer.params.at(0.0)
        arrays = [x.numpy() for x in (g.means, g.quats, g.scales, g.opacities.reshape(-1), g.features)]
        t0 = time.perf_counter()
        _, alpha, _ = draw(*arrays, ds.cameras[1])
        print(f"the runtime's splatter draws these Gaussians for one camera in {time.perf_counter() - t0:.2f} s "
              f"(mean alpha {alpha.mean():.2f})", flush=True)
    reset_peak_rss()
    t0 = time.perf_counter()
    for _ in range(args.steps):
        trainer.train_step()
    seconds = (time.perf_counter() - t0) / args.steps
    print(f"seconds per step  {seconds:.2f}\npeak memory during the steps  {peak_rss_gb():.2f} GB")


if __name__ == "__main__":
    main()
