#!/usr/bin/env python
"""Frames per second of the runtime (Player.render) for lite and full models, with each step's time
(time evaluation; the splat's projection, depth sort, tile binning and compositing; colour: the lite
clamp or the full model's decoder) and the scene's rendering load beside every figure.

    python bench/render.py [--scene like-trained|trained|random] [--gaussians 100000]
                           [--size 640x360[,1352x1014]] [--repeats 20] [--threads N]
    python bench/render.py --device cuda [--scene ...] [--gaussians 200000] [--size 1352x1014] [--no-gsplat]

Scenes (--scene):
- like-trained (default): stg_runtime.demo.like_trained_model, --gaussians Gaussians whose load is a
  trained model's: about 50 Gaussians composited per pixel, footprints that scale with the image.
- trained: a model trained by the project: the demo's (`stg-train --demo --model lite|full`, trained
  once into --cache and kept), or --model FILE.stg; seen from its first camera, rescaled to --size.
- random: stg_runtime.demo.random_model, footprints of --radius pixels whatever the size (about one
  layer per pixel at 100k and 640x360): the scenes of the project's earlier figures.

The load (stg_runtime.render_load at mid-clip): Gaussians composited per pixel before it stops (mean,
99th percentile), the mean footprint in pixels, Gaussians in view. Timings: median of --repeats
wall-clock frames after a warm-up, each at a new time; the steps are timed in a second pass over the
same frames. The float64 spec splatter (stg_runtime.spec.rasterize_oracle) is timed against the numba
one on a small scene of the same kind (--reference-size), for a ratio measured in the same run.

--device cuda times the numba.cuda path (stg_runtime.cuda: Player(device="cuda") with
render(out="device"), i.e. without the copy to the host; from one camera, and from a new camera every
frame along an orbit) and its steps (the splat with either device sort and a kept Workspace, the fused
and the onnxruntime decoder), and gsplat's rasterization of the same Gaussians where gsplat and torch
with CUDA are installed. It needs a real GPU.

The header line names the CPU (lscpu), its vector width and the one numba generates code for
(bench/machine.py says how to take the AVX2 figure on an AVX-512 machine).
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

import numba
import numpy as np

from machine import describe
from stg_runtime import Player
from stg_runtime import format as stg_format
from stg_runtime.camera import Camera
from stg_runtime.decoder import lite_colour
from stg_runtime.demo import like_trained_model, random_model
from stg_runtime.model import Model
from stg_runtime.render_load import render_load, scene_load
from stg_runtime.splat_cpu import rasterize, stage_seconds
from stg_runtime.spec import rasterize_oracle
from stg_runtime.timeeval import evaluate


def median_seconds(fn, repeats: int, clock=time.perf_counter) -> float:
    """Median seconds by `clock` of fn() over `repeats` runs, after one warm-up call."""
    fn()
    times = []
    for _ in range(repeats):
        start = clock()
        fn()
        times.append(clock() - start)
    return float(np.median(times))


def cuda_main(args, sizes, kinds, counts) -> None:
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

    name = cuda.get_current_device().name
    print(f"GPU: {name.decode() if isinstance(name, bytes) else name}; "
          f"numba {numba.__version__}; device sort: {'CuPy' if device.cupy() is not None else 'numba radix'}")
    print(f"scene: {args.scene}, median of {args.repeats} renders (output left on the GPU)\n")
    print("ms/frame: Player.render from one camera; moving: from a new camera every frame; splat ms: with "
          "the sort above; numba sort: the same splat with stg_runtime.cuda.sort's radix sort; decode: fused "
          "kernel; onnx: onnxruntime " + ("CUDA provider" if cuda_provider_available() else
                                          "CPU provider, through the host") + "\n")
    print(f"{'model':<8}{'size':>10}{'N':>8}{'FPS':>8}{'ms/frame':>10}{'moving':>8}{'eval ms':>9}{'splat ms':>10}"
          f"{'numba sort':>12}{'decode ms':>11}{'onnx ms':>9}{'gsplat ms':>11}{'layers':>8}{'p99':>5}{'foot':>7}"
          f"{'in view':>9}")

    def step_ms(fn, repeats):
        fn()
        with splat_cuda.stage_seconds() as seconds:
            for _ in range(repeats):
                fn()
        return {step: 1000 * s / repeats for step, s in seconds.items()}

    steps = []
    for n, (w, h), kind in ((n, size, kind) for n in counts for size in sizes for kind in kinds):
        model, cam, label = scene(args, kind, w, h, n)
        player = Player(model, device="cuda")
        seg = model.segments[0]
        load = scene_load(model, cam, player.start_time + 0.5 * player.duration)
        warm_until = time.perf_counter() + 1.0  # an idle GPU clocks down: a second of work first
        while time.perf_counter() < warm_until:
            player.render(cam, 0.0, out="device")
        ts = iter(player.start_time + np.linspace(0, player.duration, 2 * args.repeats + 2))
        total = gpu_seconds(lambda: player.render(cam, next(ts), out="device"), args.repeats)
        path = iter(orbit([cam], 2 * args.repeats + 2))
        ts = iter(player.start_time + np.linspace(0, player.duration, 2 * args.repeats + 2))
        moving = gpu_seconds(lambda: player.render(next(path), next(ts), out="device"), args.repeats)
        dseg = DeviceSegment(seg)
        t_eval = gpu_seconds(lambda: dseg.evaluate(0.5), args.repeats)
        g = dseg.evaluate(0.5)
        ws = {sort: memory.Workspace() for sort in ("auto", "numba")}
        t_splat = gpu_seconds(lambda: splat_cuda.rasterize(*g, cam, out="device", workspace=ws["auto"]), args.repeats)
        t_numba_sort = gpu_seconds(lambda: splat_cuda.rasterize(*g, cam, out="device", sort="numba",
                                                                workspace=ws["numba"]), args.repeats)
        for sort in ("auto", "numba"):
            steps.append((f"{kind} {w}x{h}, {sort}",
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
        print(f"{kind:<8}{f'{w}x{h}':>10}{seg.count:>8}{1 / total:>8.1f}{1000 * total:>10.2f}{1000 * moving:>8.2f}"
              f"{1000 * t_eval:>9.2f}{1000 * t_splat:>10.2f}"
              f"{1000 * t_numba_sort:>12.2f}{1000 * t_dec:>11.2f}{1000 * t_onnx:>9.2f}{gs}"
              f"{load.mean_layers:>8.1f}{load.p99_layers:>5.0f}{load.mean_footprint:>7.0f}{load.in_view:>9}", flush=True)
    print(f"({label})")
    names = list(steps[0][1])
    print("\nsplat steps, ms (the device synchronised after each step, so they add up to a little more than "
          "the splat):")
    print(f"{'':<26}" + "".join(f"{n:>13}" for n in names))
    for label, ms in steps:
        print(f"{label:<26}" + "".join(f"{ms.get(n, 0.0):>13.3f}" for n in names))


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


def scene_camera(camera: Camera, width: int, height: int) -> Camera:
    """`camera` at width x height: its focal length scaled by the width, the picture cropped (or
    extended) about its centre vertically, so that a 4:3 training camera gives a 16:9 frame."""
    s = width / camera.width
    return Camera(camera.fx * s, camera.fy * s, camera.cx * s, camera.cy * s - (camera.height * s - height) / 2,
                  width, height, camera.world_to_camera, camera.name, camera.model, camera.distortion)


def trained_model(kind: str, cache: Path, path: str | None = None) -> Model:
    """The trained model: `path` if given, else the demo's (`stg-train --demo --model KIND`), trained
    once into `cache`/demo-KIND and kept there."""
    if path is None:
        folder = cache / f"demo-{kind}"
        path = folder / "model.stg"
        if not path.exists():
            print(f"training the demo's {kind} model once into {folder} (stg-train --demo: a few minutes)",
                  flush=True)
            done = subprocess.run([sys.executable, "-m", "stg_train.cli.train", "--demo", "--model", kind,
                                   "--out", str(folder)], stdout=subprocess.DEVNULL)
            if done.returncode:
                raise SystemExit(f"bench/render.py: training the demo's {kind} model into {folder} failed "
                                 f"(exit {done.returncode}); delete the folder and retry")
    return stg_format.load(path)


def scene(args, kind: str, width: int, height: int, n: int) -> tuple[Model, Camera, str]:
    """The model of --scene for `kind` (n Gaussians where generated), the camera to render it from and a
    description."""
    if args.scene == "trained":
        model = trained_model(kind, Path(args.cache), args.model)
        cam = scene_camera(model.cameras[0], width, height)
        return model, cam, f"trained model ({model.segments[0].count} Gaussians, {model.cameras[0].name} rescaled)"
    if args.scene == "like-trained":
        model = like_trained_model(n, width, height, kind)
        return model, model.cameras[0], "stg_runtime.demo.like_trained_model"
    model = random_model(n, kind, width=width, height=height, radius_px=args.radius_px)
    return model, model.cameras[0], f"stg_runtime.demo.random_model, radius {args.radius} px"


def frame_steps(player: Player, camera: Camera, times, clock) -> dict:
    """Median milliseconds by `clock` of each step of player.render (time evaluation, the splat's
    steps, colour), each frame at the next of `times`, after a first frame that is not counted."""
    rows = []
    for t in times:
        segment, tau = player.model.segment_at(t)
        lap = clock()
        g = evaluate(segment, tau)
        ms = {"eval": clock() - lap}
        with stage_seconds(clock) as stages:
            feats = rasterize(g.means, g.quats, g.scales, g.opacities, g.features, camera)[0]
        ms.update(stages)
        lap = clock()
        player._decoder(segment)(feats, camera) if player.kind == "full" else lite_colour(feats)
        ms["colour"] = clock() - lap
        rows.append(ms)
    return {k: 1000 * float(np.median([r[k] for r in rows[1:]])) for k in rows[0]}


def frame_seconds(player: Player, camera: Camera, times) -> tuple[float, float]:
    """Median wall-clock and CPU seconds (the process's, all threads) of player.render, each frame at
    the next of `times`, after a first frame that is not counted."""
    wall, cpu = [], []
    for t in times:
        w, c = time.perf_counter(), time.process_time()
        player.render(camera, t)
        wall.append(time.perf_counter() - w)
        cpu.append(time.process_time() - c)
    return float(np.median(wall[1:])), float(np.median(cpu[1:]))


STEPS = ("eval", "project", "sort", "bin", "composite", "colour")
COLUMN = 10


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", choices=["like-trained", "trained", "random"], default="like-trained",
                    help="like-trained: stg_runtime.demo.like_trained_model (default); trained: a trained model "
                         "(--model, else the demo's, trained once into --cache); random: random_model")
    ap.add_argument("--gaussians", default="100000", help="Gaussians of the generated scenes; several: "
                    "100000,200000")
    ap.add_argument("--size", default="640x360", help="WxH of the timed renders; several: 640x360,1352x1014")
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--kinds", default="lite,full", help="models to time (default lite,full)")
    ap.add_argument("--load-only", action="store_true", help="print the scenes' load statistics, time nothing")
    ap.add_argument("--model", default=None, help="with --scene trained: this .stg instead of the demo's")
    ap.add_argument("--cache", default="out/bench_cache", help="where --scene trained keeps the demo's models")
    ap.add_argument("--radius", default="0.5,10", help="--scene random: 3-sigma radius range in pixels, LO,HI")
    ap.add_argument("--threads", type=int, default=0, help="numba threads (default: numba's default)")
    ap.add_argument("--clock", choices=["wall", "cpu"], default="wall",
                    help="the steps' clock: wall-clock, or the process's CPU time (all threads; with "
                         "--threads 1 the figure that holds on a shared machine)")
    ap.add_argument("--reference-size", default="64x48", help="WxH for the float64 reference splatter")
    ap.add_argument("--reference-gaussians", type=int, default=2000)
    ap.add_argument("--device", choices=["cpu", "cuda"], default="cpu",
                    help="cuda: time the numba.cuda path on the GPU (needs a real GPU)")
    ap.add_argument("--no-gsplat", dest="gsplat", action="store_false",
                    help="with --device cuda: skip gsplat (whose first use compiles its kernels)")
    args = ap.parse_args()
    args.radius_px = tuple(float(v) for v in args.radius.split(","))
    sizes = [tuple(int(v) for v in size.lower().split("x")) for size in args.size.split(",")]
    kinds = args.kinds.split(",")
    if args.scene == "trained" and args.model:
        kinds = [stg_format.load(args.model).kind]  # the file's own kind
    counts = [int(v) for v in args.gaussians.split(",")] if args.scene != "trained" else [0]
    if args.load_only:
        return load_main(args, sizes, counts, kinds[0])
    if args.device == "cuda":
        return cuda_main(args, sizes, kinds, counts)
    if args.threads:
        numba.set_num_threads(args.threads)
    print(f"{describe()}; numba {numba.__version__}, {numba.get_num_threads()} threads")
    print(f"scene: {args.scene}; median of {args.repeats} frames, each at a new time: FPS and ms wall-clock, "
          f"cpu ms the process's CPU time; step times ({args.clock} ms) from a second pass over the same "
          f"frames; load: Gaussians composited per pixel (mean, p99), mean footprint (pixels), Gaussians in "
          f"view (stg_runtime.render_load at mid-clip)\n")
    clock = time.perf_counter if args.clock == "wall" else time.process_time
    print(f"{'model':<6}{'size':>10}{'N':>8}{'FPS':>7}{'ms':>7}{'cpu ms':>8}" + "".join(f"{s:>{COLUMN}}" for s in STEPS)
          + f"{'layers':>8}{'p99':>5}{'foot':>7}{'in view':>9}")
    for n, (w, h), kind in ((n, size, kind) for n in counts for size in sizes for kind in kinds):
        model, cam, label = scene(args, kind, w, h, n)
        player = Player(model, device="cpu")
        times = player.start_time + np.linspace(0, player.duration, args.repeats + 1)
        total, cpu = frame_seconds(player, cam, times)
        steps = frame_steps(player, cam, times, clock)
        load = scene_load(model, cam, player.start_time + 0.5 * player.duration)
        print(f"{kind:<6}{f'{w}x{h}':>10}{model.segments[0].count:>8}{1 / total:>7.1f}{1000 * total:>7.1f}"
              f"{1000 * cpu:>8.1f}"
              + "".join(f"{steps[s]:>{COLUMN}.1f}" for s in STEPS)
              + f"{load.mean_layers:>8.1f}{load.p99_layers:>5.0f}{load.mean_footprint:>7.0f}{load.in_view:>9}",
              flush=True)
    print(f"({label})")
    reference(args, kinds[0], clock)


def load_main(args, sizes, counts, kind) -> None:
    """--load-only: the load statistics of each scene (count x size), no timing."""
    print(f"scene: {args.scene}; load at mid-clip (stg_runtime.render_load)\n")
    print(f"{'size':>10}{'Gaussians':>10}{'in view':>9}{'layers':>8}{'p99':>5}{'footprint px':>14}"
          f"{'image %':>9}{'tile entries':>14}")
    for n, (w, h) in ((n, size) for n in counts for size in sizes):
        model, cam, label = scene(args, kind, w, h, n)
        load = scene_load(model, cam, model.start_frame / model.fps + 0.5 * model.duration)
        print(f"{f'{w}x{h}':>10}{model.segments[0].count:>10}{load.in_view:>9}{load.mean_layers:>8.1f}"
              f"{load.p99_layers:>5.0f}{load.mean_footprint:>14.0f}{100 * load.mean_footprint / (w * h):>9.3f}"
              f"{load.tile_entries:>14}", flush=True)
    print(f"({label})")


def reference(args, kind: str, clock) -> None:
    """The float64 spec splatter against the numba one on a small scene of the same kind, one run."""
    rw, rh = (int(v) for v in args.reference_size.lower().split("x"))
    if args.scene == "trained":
        model = trained_model(kind, Path(args.cache), args.model)
        cam = scene_camera(model.cameras[0], rw, rh)
    elif args.scene == "like-trained":
        model = like_trained_model(args.reference_gaussians, rw, rh, kind, seed=1)
        cam = model.cameras[0]
    else:
        model = random_model(args.reference_gaussians, kind, width=rw, height=rh, seed=1)
        cam = model.cameras[0]
    g = evaluate(model.segments[0], 0.5)
    arrays = (g.means, g.quats, g.scales, g.opacities, g.features[:, :3], cam)
    t_ref = median_seconds(lambda: rasterize_oracle(*arrays), 1, clock)
    t_fast = median_seconds(lambda: rasterize(*arrays), 5, clock)
    load = render_load(*arrays[:4], cam)
    print(f"\nfloat64 reference splatter (stg_runtime.spec.rasterize_oracle), {len(g.opacities)} Gaussians at "
          f"{rw}x{rh} ({load.summary()}): {1000 * t_ref:.0f} {args.clock} ms/frame; the numba splatter on the same: "
          f"{1000 * t_fast:.2f} ms, {t_ref / t_fast:.0f}x faster")


if __name__ == "__main__":
    main()
