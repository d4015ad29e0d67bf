#!/usr/bin/env python
"""The training splatters through a fisheye against a pinhole with the same intrinsics: seconds per
forward + backward pass, and of the projection alone, back to back.

    python bench/fisheye_splat.py [--gaussians 50000] [--size 320x240] [--repeats 5] [--threads 2]

Scene: Gaussians uniform in a frustum of about 60 degrees between depths 2 and 6, standard deviations
0.005..0.03 (a few pixels), opacity 0.1..0.9, rgb features. The fisheye has k1 = 0.01. Printed: the
median of --repeats passes after a warm-up (numba's JIT compiled or loaded from its cache first), for
the numba splatter, then for the projections alone (numba and torch).
"""
from __future__ import annotations

import argparse
import time

import stg_train  # noqa: F401  (before torch: its OpenMP setting)
import numba
import numpy as np
import torch

from stg_runtime.camera import Camera
from stg_train.render import rasterize
from stg_train.render.numba_splat import Project
from stg_train.render.torch_splat import project


def scene(n: int, seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    z = rng.uniform(2, 6, n)
    means = np.concatenate([rng.uniform(-0.6, 0.6, (n, 2)) * z[:, None], z[:, None]], 1)
    return [means, rng.normal(size=(n, 4)), rng.uniform(0.005, 0.03, (n, 3)), rng.uniform(0.1, 0.9, n),
            rng.uniform(0, 1, (n, 3))]


def seconds(fn, repeats: int) -> float:
    fn()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--gaussians", type=int, default=50_000)
    ap.add_argument("--size", default="320x240")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    numba.set_num_threads(args.threads)
    width, height = map(int, args.size.split("x"))
    pinhole = Camera.look_at([0, 0, 0], [0, 0, 1], [0, -1, 0], 60.0, width, height)
    fisheye = Camera(pinhole.fx, pinhole.fy, pinhole.cx, pinhole.cy, width, height, pinhole.world_to_camera, "",
                     "fisheye", (0.01, 0.0, 0.0, 0.0))
    arrays = scene(args.gaussians)

    def step(camera):
        inputs = [torch.tensor(a, dtype=torch.float32, requires_grad=True) for a in arrays]
        out = rasterize(*inputs, camera, backend="numba")
        (out.features.sum() + out.alpha.sum()).backward()

    def projection(camera, fn):
        inputs = [torch.tensor(a, dtype=torch.float32, requires_grad=True) for a in arrays[:4]]
        out = fn(*inputs, camera)
        (out[0].sum() + out[1].sum() + out[2].sum()).backward()

    print(f"{args.gaussians} Gaussians, {width}x{height}, {args.threads} threads, median of {args.repeats}")
    base = seconds(lambda: step(pinhole), args.repeats)
    fish = seconds(lambda: step(fisheye), args.repeats)
    print(f"numba splatter forward + backward: pinhole {base * 1e3:.1f} ms, fisheye {fish * 1e3:.1f} ms "
          f"({fish / base:.2f}x)")
    for name, fn in (("numba", Project.apply), ("torch", project)):
        p = seconds(lambda: projection(pinhole, fn), args.repeats)
        f = seconds(lambda: projection(fisheye, fn), args.repeats)
        print(f"{name} projection forward + backward: pinhole {p * 1e3:.1f} ms, fisheye {f * 1e3:.1f} ms")


if __name__ == "__main__":
    main()
