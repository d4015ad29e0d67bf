#!/usr/bin/env python
"""Where a GPU frame's time goes: each kernel's time on the GPU (CUPTI, through torch's profiler) for
stg_runtime.cuda.splat.rasterize with a kept Workspace at the benchmark size, and the host's cost of
each kind of call a frame can make. Needs a real GPU, CuPy, and torch with CUDA (for its profiler only).

    python bench/gpu_profile.py [--gaussians 200000] [--size 1352x1014] [--trace OUTDIR]

Prints, per model (lite: 3 channels, full: 9): the wall-clock ms of a frame, the ms the GPU was busy
(the union of kernel intervals) and each kernel's mean us and launches per frame; then the host cost
of a plain numba launch and of a replayed one (stg_runtime.cuda.launch), of allocations, a
synchronisation, a device-to-host scalar read and some CuPy calls; then the GPU time of CuPy's sorts
by key width. A frame whose GPU-busy time is well under its wall-clock time is bound by the host.
"""
from __future__ import annotations

import argparse
import json
import time
from collections import defaultdict
from pathlib import Path

import numpy as np


def host_us(fn, n=300) -> float:
    """Mean host microseconds of fn() over n calls (the device synchronised before and after)."""
    from numba import cuda
    fn()
    cuda.synchronize()
    t = time.perf_counter()
    for _ in range(n):
        fn()
    dt = time.perf_counter() - t
    cuda.synchronize()
    return 1e6 * dt / n


def kernel_table(trace_file: Path, frames: int):
    """(busy ms per frame, wall ms per frame, [(name, launches per frame, mean us)]) from a chrome trace."""
    events = json.loads(trace_file.read_text())["traceEvents"]
    kernels = [e for e in events if e.get("cat") in ("kernel", "gpu_memcpy", "gpu_memset")]
    if not kernels:
        return None
    spans = sorted((e["ts"], e["ts"] + e["dur"]) for e in kernels)
    busy, end = 0.0, -1e30
    for s, e in spans:
        if e > end:
            busy += e - max(s, end)
            end = e
    by_name = defaultdict(list)
    for e in kernels:
        by_name[e["name"][:60]].append(e["dur"])
    rows = sorted(((n, len(d) / frames, float(np.mean(d))) for n, d in by_name.items()), key=lambda r: -r[1] * r[2])
    return busy / 1000 / frames, rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--gaussians", type=int, default=200_000)
    ap.add_argument("--size", default="1352x1014")
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--trace", default="", help="folder for the chrome traces (default: none kept)")
    args = ap.parse_args()
    import torch  # noqa: F401 (its CUDA context first; the profiler)
    from torch.profiler import ProfilerActivity, profile
    import cupy
    from numba import cuda

    from stg_runtime.camera import orbit
    from stg_runtime.cuda import decoder as decoder_cuda
    from stg_runtime.cuda import memory
    from stg_runtime.cuda import splat as splat_cuda
    from stg_runtime.cuda.timeeval import DeviceSegment
    from stg_runtime.demo import random_model
    from stg_runtime.projection import camera_params

    torch.zeros(1, device="cuda")
    w, h = (int(v) for v in args.size.lower().split("x"))
    out = Path(args.trace) if args.trace else Path("/tmp/stg_trace")
    out.mkdir(parents=True, exist_ok=True)
    print(f"{args.gaussians} Gaussians at {w}x{h}; {args.frames} frames profiled\n")
    for kind in ("lite", "full"):
        model = random_model(args.gaussians, kind, width=w, height=h)
        cam = model.cameras[0]
        g = DeviceSegment(model.segments[0]).evaluate(0.5)
        ws = memory.Workspace()
        for _ in range(5):
            splat_cuda.rasterize(*g, cam, out="device", workspace=ws)
        cuda.synchronize()
        t = time.perf_counter()
        for _ in range(args.frames):
            splat_cuda.rasterize(*g, cam, out="device", workspace=ws)
        cuda.synchronize()
        wall = 1000 * (time.perf_counter() - t) / args.frames
        with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
            for _ in range(args.frames):
                splat_cuda.rasterize(*g, cam, out="device", workspace=ws)
            cuda.synchronize()
        trace = out / f"trace_{kind}.json"
        prof.export_chrome_trace(str(trace))
        table = kernel_table(trace, args.frames)
        print(f"{kind}: {wall:.3f} ms per frame (wall clock, unprofiled)")
        if table is None:
            print("  (no kernels in the profiler's trace)")
            continue
        busy, rows = table
        print(f"  GPU busy {busy:.3f} ms per frame (profiled)")
        for name, per_frame, us in rows:
            print(f"  {us:9.1f} us x {per_frame:4.1f}  {name}")
        print()

    # Host costs of the calls a frame makes.
    from stg_runtime.cuda.launch import launch
    keys = cuda.device_array(1024, np.int32)
    order = cuda.device_array((1024, 2), np.int32)
    counters = cuda.to_device(np.zeros(3, np.int64))  # no entries: the kernel does nothing
    ranges = cuda.device_array((64, 2), np.int64)
    ids = cuda.device_array(1024, np.int32)
    ranges_args = (keys, order, counters, ranges, ids)
    cams = [camera_params(c) for c in orbit(model.cameras, 2)]
    empty = cuda.device_array((0, 3), np.float32)  # _sh over no Gaussians: only the launch
    costs = {
        "numba launch, 5 array args (_ranges)": lambda: splat_cuda._ranges[4, 256](*ranges_args),
        "launch of _ranges (replayed)": lambda: launch(splat_cuda._ranges, 4, 256, *ranges_args),
        "numba launch, 1 array arg (_clear)": lambda: splat_cuda._clear[1, 32](counters),
        "launch of _clear (replayed)": lambda: launch(splat_cuda._clear, 1, 32, counters),
        "launch, a new 19-float camera every call": (
            lambda: launch(decoder_cuda._sh, 1, 32, empty, empty, cams.reverse() or cams[0], empty)),
        "cupy.empty": lambda: cupy.empty((200000, 7), np.float32),
        "memory.device_empty (cupy.empty + numba view)": lambda: memory.device_empty((200000, 7), np.float32),
        "numba cuda.device_array": lambda: cuda.device_array((200000, 7), np.float32),
        "cuda.synchronize (idle)": cuda.synchronize,
        "int(cupy_array[-1])": lambda a=cupy.arange(10): int(a[-1]),
        "cupy elementwise (a - b)": lambda a=cupy.arange(200000), b=cupy.arange(200000): a - b,
        "cupy.cumsum 200k int64": lambda a=cupy.arange(200000): cupy.cumsum(a),
        "camera_params": lambda: camera_params(cam),
    }
    print("host cost per call (us):")
    for name, fn in costs.items():
        try:
            print(f"  {host_us(fn):8.1f}  {name}")
        except Exception as e:  # noqa: BLE001 (a probe may not apply on this stack)
            print(f"  failed: {name}: {type(e).__name__}: {e}")

    # GPU time of the sorts, by key width.
    def gpu_ms(fn, n=50):
        fn()
        start, stop = cupy.cuda.Event(), cupy.cuda.Event()
        start.record()
        for _ in range(n):
            fn()
        stop.record()
        stop.synchronize()
        return cupy.cuda.get_elapsed_time(start, stop) / n

    r = cupy.random.default_rng(0)
    d64 = r.random(args.gaussians) * 10
    pairs = 3 * args.gaussians
    k64 = r.integers(0, 2**30, pairs, dtype=cupy.int64)
    print("\nGPU ms per call (events, queued back to back):")
    for name, fn in {
        f"argsort {args.gaussians} float64": lambda: cupy.argsort(d64),
        f"argsort {args.gaussians} float32": lambda: cupy.argsort(d64.astype(cupy.float32)),
        f"sort {pairs} int64 (copy + in place)": lambda: k64.copy().sort(),
        f"sort {pairs} int32 (copy + in place)": lambda: k64.astype(cupy.int32).sort(),
        f"copy {pairs} int64": lambda: k64.copy(),
    }.items():
        print(f"  {gpu_ms(fn):8.3f}  {name}")


if __name__ == "__main__":
    main()
