#!/usr/bin/env python
"""Frames per second of the CPU runtime (Player.render) for lite and full models of N Gaussians, with a
breakdown (time evaluation, splatting, decoder), beside the float64 numpy reference splatter.

    python bench/render.py [--gaussians 100000] [--size 640x360] [--repeats 20] [--threads N]
    python bench/render.py --device cuda [--gaussians 200000] [--size 1352x1014] [--no-gsplat]

--device cuda times the numba.cuda path (stg_runtime.cuda: Player(device="cuda") with
render(out="device"), i.e. without the copy to the host; from one camera, and from a new camera every
frame along an orbit) and its steps (the splat with either device sort and a kept Workspace, the fused
and the onnxruntime decoder), and gsplat's rasterization of the same Gaussians where gsplat and torch
with CUDA are installed. It needs a real GPU.

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
from stg_runtime.spec import project_oracle, rasterize_oracle
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


def cuda_main(args) -> None:
    """The GPU benchmark (--device cuda): FPS of Player(device="cuda"), breakdown, gsplat beside it."""
    from stg_runtime.cuda import device, memory
    from stg_runtime.cuda import splat as splat_cuda
    if not device.gpu_available():
        raise SystemExit("bench/render.py --device cuda: numba sees no CUDA GPU here"
                         + (" (NUMBA_ENABLE_CUDASIM=1 is set: the simulator cannot be timed)"
                            if device.simulated() else "") + "; run it on a machine with an NVIDIA GPU")
    from numba import cuda

    from stg_runtime.camera import orbit
    from stg_runtime.cuda.decoder import FusedDecoder, OnnxDeviceDecoder, cuda_provider_available
    from stg_runtime.cuda.timeeval import DeviceSegment

    def gpu_seconds(fn, repeats):
        return median_seconds(lambda: (fn(), cuda.synchronize()), repeats)

    w, h = (int(v) for v in args.size.lower().split("x"))
    name = cuda.get_current_device().name
    print(f"GPU: {name.decode() if isinstance(name, bytes) else name}; "
          f"numba {numba.__version__}; device sort: {'CuPy' if device.cupy() is not None else 'numba radix'}")
    print(f"{args.gaussians} Gaussians at {w}x{h}, median of {args.repeats} renders (output left on the GPU)\n")
    print("ms/frame: Player.render from one camera; moving: from a new camera every frame; splat ms: with "
          "the sort above; numba sort: the same splat with stg_runtime.cuda.sort's radix sort; decode: fused "
          "kernel; onnx: onnxruntime " + ("CUDA provider" if cuda_provider_available() else
                                          "CPU provider, through the host") + "\n")
    print(f"{'model':<8}{'FPS':>8}{'ms/frame':>10}{'moving':>8}{'eval ms':>9}{'splat ms':>10}{'numba sort':>12}"
          f"{'decode ms':>11}{'onnx ms':>9}{'gsplat ms':>11}")

    def step_ms(fn, repeats):
        fn()
        with splat_cuda.stage_seconds() as seconds:
            for _ in range(repeats):
                fn()
        return {step: 1000 * s / repeats for step, s in seconds.items()}

    radius_px = tuple(float(v) for v in args.radius.split(","))
    steps = []
    for kind in ("lite", "full"):
        model = random_model(args.gaussians, kind, width=w, height=h, radius_px=radius_px)
        player = Player(model, device="cuda")
        cam, seg = model.cameras[0], model.segments[0]
        warm_until = time.perf_counter() + 1.0  # an idle GPU clocks down: a second of work first
        while time.perf_counter() < warm_until:
            player.render(cam, 0.0, out="device")
        ts = iter(np.linspace(0, player.duration, 2 * args.repeats + 2))
        total = gpu_seconds(lambda: player.render(cam, next(ts), out="device"), args.repeats)
        path = iter(orbit(model.cameras, 2 * args.repeats + 2))
        ts = iter(np.linspace(0, player.duration, 2 * args.repeats + 2))
        moving = gpu_seconds(lambda: player.render(next(path), next(ts), out="device"), args.repeats)
        dseg = DeviceSegment(seg)
        t_eval = gpu_seconds(lambda: dseg.evaluate(0.5), args.repeats)
        g = dseg.evaluate(0.5)
        ws = {sort: memory.Workspace() for sort in ("auto", "numba")}
        t_splat = gpu_seconds(lambda: splat_cuda.rasterize(*g, cam, out="device", workspace=ws["auto"]), args.repeats)
        t_numba_sort = gpu_seconds(lambda: splat_cuda.rasterize(*g, cam, out="device", sort="numba",
                                                                workspace=ws["numba"]), args.repeats)
        for sort in ("auto", "numba"):
            steps.append((f"{kind}, {sort} sort",
                          step_ms(lambda: splat_cuda.rasterize(*g, cam, out="device", sort=sort, workspace=ws[sort]),
                                  args.repeats)))
        t_dec = t_onnx = 0.0
        if kind == "full":
            feats = splat_cuda.rasterize(*g, cam, out="device", workspace=ws["auto"])[0]
            fused = FusedDecoder.from_onnx(seg.decoder, seg.activation)
            rgb = memory.device_empty((h, w, 3), np.float32)
            t_dec = gpu_seconds(lambda: fused(feats, cam, out=rgb), args.repeats)
            onnx = OnnxDeviceDecoder(seg.decoder, seg.activation)
            t_onnx = gpu_seconds(lambda: onnx(feats, cam), args.repeats)
        t_gsplat = _gsplat_seconds([a.copy_to_host() for a in g], cam, args.repeats) if args.gsplat else None
        gs = f"{1000 * t_gsplat:>11.2f}" if t_gsplat else f"{'n/a':>11}"
        print(f"{kind:<8}{1 / total:>8.1f}{1000 * total:>10.2f}{1000 * moving:>8.2f}{1000 * t_eval:>9.2f}"
              f"{1000 * t_splat:>10.2f}"
              f"{1000 * t_numba_sort:>12.2f}{1000 * t_dec:>11.2f}{1000 * t_onnx:>9.2f}{gs}")
    names = list(steps[0][1])
    print("\nsplat steps, ms (the device synchronised after each step, so they add up to a little more than "
          "the splat):")
    print(f"{'':<20}" + "".join(f"{n:>13}" for n in names))
    for label, ms in steps:
        print(f"{label:<20}" + "".join(f"{ms.get(n, 0.0):>13.3f}" for n in names))


def _gsplat_seconds(arrays, camera, repeats) -> float | None:
    """Median seconds of gsplat's rasterization of the same Gaussians (opacity-culled as ours), or None
    (with the reason printed) when gsplat or torch with CUDA is missing."""
    try:
        from stg_train.render.gsplat_backend import rasterize_gsplat, unavailable_reason  # before torch (stg_train's rule)
        import torch
    except ImportError as e:
        print(f"(gsplat skipped: {e})")
        return None
    reason = unavailable_reason("cuda")
    if reason:
        print(f"(gsplat skipped: {reason})")
        return None
    tensors = [torch.as_tensor(a, device="cuda") for a in arrays]

    def run():
        with torch.no_grad():
            rasterize_gsplat(*tensors, camera)
        torch.cuda.synchronize()
    return median_seconds(run, repeats)


def layers(g, camera) -> float:
    """Mean number of 1-sigma ellipses (2D covariance with blur) over a pixel."""
    p = project_oracle(g.means, g.quats, g.scales, camera)
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
    ap.add_argument("--device", choices=["cpu", "cuda"], default="cpu",
                    help="cuda: time the numba.cuda path on the GPU (needs a real GPU)")
    ap.add_argument("--no-gsplat", dest="gsplat", action="store_false",
                    help="with --device cuda: skip gsplat (whose first use compiles its kernels)")
    args = ap.parse_args()
    if args.device == "cuda":
        return cuda_main(args)
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
    t_ref = median_seconds(lambda: rasterize_oracle(g.means, g.quats, g.scales, g.opacities, g.features, cam), 1)
    t_fast = median_seconds(lambda: rasterize(g.means, g.quats, g.scales, g.opacities, g.features, cam), 5)
    print(f"\nnumpy reference, {args.reference_gaussians} Gaussians at {rw}x{rh}: {1000 * t_ref:.0f} ms/frame "
          f"(numba splatter on the same: {1000 * t_fast:.2f} ms, {t_ref / t_fast:.0f}x faster)")


if __name__ == "__main__":
    main()
