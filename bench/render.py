#!/usr/bin/env python
"""Frames per second of the CPU runtime (Player.render) for lite and full models of N Gaussians, with a
breakdown (time evaluation, splatting, decoder), beside the float64 numpy reference splatter.

    python bench/render.py [--gaussians 100000] [--size 640x360] [--repeats 20] [--threads N]

Scenes come from stg_runtime.demo.random_model: Gaussians uniform in the volume of a 60-degree frustum
between depths 2 and 10, projected 3-sigma radius log-uniform in --radius pixels (default 0.5..10,
footprints 1 to 20 px across), opacity 0.1..0.9, a little motion over the clip. A "deep" scene uses
--deep-radius (default 1..20 px: about four times as many layers per pixel). Each render is at a new
time (swept over the clip), so time evaluation is included. Timings: median of --repeats wall-clock
frames after a warm-up (numba's JIT compiled or loaded from its cache first).
"""
from __future__ import annotations

import argparse
import os
import platform
import time

import numba
import numpy as np

from stg_runtime import Player
from stg_runtime.demo import random_model
from stg_runtime.splat_cpu import rasterize
from stg_runtime.splat_reference import project_reference, rasterize_reference
from stg_runtime.timeeval import evaluate


def median_seconds(fn, repeats: int) -> float:
    """Median seconds of fn() over `repeats` runs, after one warm-up call."""
    fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return float(np.median(times))


def layers(g, camera) -> float:
    """Mean number of 1-sigma ellipses (2D covariance with blur) over a pixel."""
    p = project_reference(g.means, g.quats, g.scales, camera)
    a, b, c = p.cov2d[p.visible].T
    return float(np.sum(np.pi * np.sqrt(a * c - b * b)) / (camera.width * camera.height))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--gaussians", type=int, default=100_000)
    ap.add_argument("--size", default="640x360", help="WxH of the timed renders")
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--radius", default="0.5,10", help="3-sigma radius range in pixels, LO,HI")
    ap.add_argument("--deep-radius", default="1,20", help="radius range of the deep scene (0: skip it)")
    ap.add_argument("--threads", type=int, default=0, help="numba threads (default: numba's default)")
    ap.add_argument("--reference-size", default="64x48", help="WxH for the numpy reference")
    ap.add_argument("--reference-gaussians", type=int, default=2000)
    args = ap.parse_args()
    if args.threads:
        numba.set_num_threads(args.threads)
    w, h = (int(v) for v in args.size.lower().split("x"))
    scenes = [("", args.radius)] + ([("deep", args.deep_radius)] if args.deep_radius != "0" else [])
    print(f"CPU: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, load average "
          f"{os.getloadavg()[0]:.2f}; numba {numba.__version__}, {numba.get_num_threads()} threads "
          f"({numba.threading_layer() if hasattr(numba, 'threading_layer') else '?'} layer)")
    print(f"{args.gaussians} Gaussians at {w}x{h}, median of {args.repeats} renders\n")
    print(f"{'model':<12}{'layers':>7}{'FPS':>8}{'ms/frame':>10}{'eval ms':>9}{'splat ms':>10}{'decode ms':>11}")
    for label, radius in scenes:
        radius_px = tuple(float(v) for v in radius.split(","))
        for kind in ("lite", "full"):
            model = random_model(args.gaussians, kind, width=w, height=h, radius_px=radius_px)
            player = Player(model, device="cpu")
            cam, seg = model.cameras[0], model.segments[0]
            ts = iter(np.linspace(0, player.duration, args.repeats + 1))
            total = median_seconds(lambda: player.render(cam, next(ts)), args.repeats)
            g = evaluate(seg, 0.5)
            t_eval = median_seconds(lambda: evaluate(seg, 0.5), args.repeats)
            t_splat = median_seconds(lambda: rasterize(g.means, g.quats, g.scales, g.opacities, g.features, cam),
                                     args.repeats)
            t_dec = 0.0
            if kind == "full":
                feats = rasterize(g.means, g.quats, g.scales, g.opacities, g.features, cam)[0]
                decoder = player._decoder(seg)
                t_dec = median_seconds(lambda: decoder(feats, cam), args.repeats)
            print(f"{(kind + ' ' + label).strip():<12}{layers(g, cam):>7.1f}{1 / total:>8.1f}{1000 * total:>10.1f}"
                  f"{1000 * t_eval:>9.1f}{1000 * t_splat:>10.1f}{1000 * t_dec:>11.1f}")

    rw, rh = (int(v) for v in args.reference_size.lower().split("x"))
    model = random_model(args.reference_gaussians, "lite", width=rw, height=rh, seed=1)
    g, cam = evaluate(model.segments[0], 0.5), model.cameras[0]
    t_ref = median_seconds(lambda: rasterize_reference(g.means, g.quats, g.scales, g.opacities, g.features, cam), 1)
    t_fast = median_seconds(lambda: rasterize(g.means, g.quats, g.scales, g.opacities, g.features, cam), 5)
    print(f"\nnumpy reference, {args.reference_gaussians} Gaussians at {rw}x{rh}: {1000 * t_ref:.0f} ms/frame "
          f"(numba splatter on the same: {1000 * t_fast:.2f} ms, {t_ref / t_fast:.0f}x faster)")


if __name__ == "__main__":
    main()
