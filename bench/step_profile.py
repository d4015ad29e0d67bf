#!/usr/bin/env python
"""Where a CPU training step's time goes, by part of the step (a reduced N3V size by default:
20 cameras at 676x507, 200k Gaussians, the numba splatter).

    python bench/step_profile.py [--cameras 20] [--width 676] [--height 507] [--gaussians 200000]
                                 [--steps 5] [--splatter numba|torch|gsplat] [--threads 2] [--ops 15]
                                 [--device cpu|cuda]

The capture is bench/step_memory.py's (frames drawn in memory by the runtime's splatter). After one
warm-up step, --steps steps run under cProfile; printed: the seconds per step of each part (the
time evaluation `STGParams.at`, the rasteriser forward, the colour decoder, the loss (L1 + SSIM), the
backward pass, with the rasteriser's own backward kernel apart, density control and guided sampling,
Adam, the ground-truth upload), then torch's own op table (torch.profiler, self CPU time) for one
more step. Parts overlap where one calls another (the backward includes the rasteriser's backward).
With --device cuda only torch's op table is printed, sorted by GPU time, over --steps steps (the
host's per-part times would be launch times).
"""
from __future__ import annotations

import argparse
import cProfile
import os
import pstats
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from step_memory import capture  # noqa: E402  (first: it imports stg_train before torch)

import torch  # noqa: E402

from stg_train.trainer import Trainer, TrainConfig  # noqa: E402

#: Printed part -> (file name suffix, function name) of the function whose cumulative time it is.
PARTS = {
    "time evaluation (STGParams.at)": ("params.py", "at"),
    "rasteriser forward": ("render/__init__.py", "rasterize"),
    "  numba composite forward": ("numba_splat.py", "forward"),
    "colour decoder (STGParams.colour)": ("params.py", "colour"),
    "loss (L1 + SSIM)": ("losses.py", "loss_fn"),
    "  SSIM": ("losses.py", "ssim"),
    "backward (all of it)": ("_tensor.py", "backward"),
    "  numba composite backward": ("numba_splat.py", "backward"),
    "density control (post-backward)": ("density.py", "step_post_backward"),
    "guided sampling (post-backward)": ("guided.py", "step_post_backward"),
    "Adam (optimizer.step)": ("adam.py", "step"),
    "ground truth (read, upload, /255)": ("trainer.py", "ground_truth"),
    "zero_grad": ("optimizer.py", "zero_grad"),
}


def part_seconds(stats: pstats.Stats, steps: int) -> dict[str, float]:
    """Cumulative seconds per step of each PARTS function (0 when it was not called)."""
    out = {}
    for label, (suffix, name) in PARTS.items():
        total = 0.0
        for (path, _, func), (_, _, _, cumulative, _) in stats.stats.items():
            if func == name and path.replace(os.sep, "/").endswith(suffix):
                total = max(total, cumulative)  # the outermost entry (recursion counted once)
        out[label] = total / steps
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cameras", type=int, default=20)
    ap.add_argument("--width", type=int, default=676)
    ap.add_argument("--height", type=int, default=507)
    ap.add_argument("--gaussians", type=int, default=200_000)
    ap.add_argument("--steps", type=int, default=5)
    ap.add_argument("--splatter", default="numba", choices=["numba", "torch", "gsplat"])
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--ops", type=int, default=15, help="rows of torch's op table")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    ds = capture(args.cameras, args.width, args.height)
    trainer = Trainer(ds, TrainConfig(num_points=args.gaussians, init="volume", depth_candidates=0,
                                      splatter=args.splatter, iterations=30_000, device=args.device))
    trainer.train_step()  # compiles the kernels
    if args.device == "cuda":
        cuda_table(trainer, args)
        return
    profiler = cProfile.Profile()
    t0 = time.perf_counter()
    profiler.enable()
    for _ in range(args.steps):
        trainer.train_step()
    profiler.disable()
    step = (time.perf_counter() - t0) / args.steps
    print(f"{ds}; {trainer.params.count} Gaussians, {args.splatter} splatter, {args.threads} threads, "
          f"load average {os.getloadavg()[0]:.1f}; {step:.2f} s per step (under cProfile)")
    for label, seconds in part_seconds(pstats.Stats(profiler), args.steps).items():
        print(f"  {label:<36} {seconds:6.3f} s  {100 * seconds / step:5.1f} %")
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
        trainer.train_step()
    print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=args.ops))


def cuda_table(trainer: Trainer, args) -> None:
    """torch.profiler's op table of --steps steps on the GPU, by self GPU time."""
    activities = [torch.profiler.ProfilerActivity.CPU, torch.profiler.ProfilerActivity.CUDA]
    torch.cuda.synchronize()
    t0 = time.perf_counter()
    with torch.profiler.profile(activities=activities) as prof:
        for _ in range(args.steps):
            trainer.train_step()
        torch.cuda.synchronize()
    print(f"{trainer.dataset}; {trainer.params.count} Gaussians, {args.splatter} splatter on "
          f"{torch.cuda.get_device_name()}; {(time.perf_counter() - t0) / args.steps:.3f} s per step (profiled)")
    print(prof.key_averages().table(sort_by="self_device_time_total", row_limit=args.ops))


if __name__ == "__main__":
    main()
