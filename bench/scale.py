#!/usr/bin/env python
"""Training at the scale of a real capture: an N3V-sized scene (20 cameras x 300 frames at 1352x1014
by default) generated on disk, then its decoding, frame cache, initialisation and training steps
measured, on the CPU and, where there is one, on a CUDA GPU.

    python bench/scale.py [--cameras 20] [--frames 300] [--width 1352] [--height 1014] [--data DIR]
                          [--workers N] [--draw-scale 1] [--segment-frames 50] [--gaussians 200000] [--steps 3]
                          [--torch-downscale 4] [--whole | --no-whole] [--device auto|cpu|cuda]
                          [--segment-iterations 30000] [--no-segment]

1. generate: a ring of cameras around random Gaussians (some moving) inside a shell of large ones,
   every frame drawn by the runtime's CPU splatter (stg_runtime.splat_cpu) in --workers processes
   (--draw-scale N: at 1/N size, then enlarged) and written as camXX.mp4 with poses_bounds.npy (the
   N3V layout, stg_train.data.n3v); kept in --data and reused while its settings match.
2. decode: the scene loaded lazily (load_dataset(lazy=True), cut into --segment-frames segments, as
   `stg-train --segment-frames` does); segment 0 decoded into its frame-cache chunk (time, size on
   disk, and the cache folders that exist afterwards: only segment 0's); with --whole (the default)
   the other segments too.
3. CPU: the view-volume initialisation of segment 0 (time, peak memory), then --steps training steps
   with the numba splatter at full size and with the torch splatter at 1/--torch-downscale size.
4. GPU (when CUDA is available or --device cuda): seconds per step and GPU peak memory with gsplat and
   with the torch splatter at full size; then segment 0 trained for --segment-iterations steps (the
   reference schedule is 30000) with gsplat, its training time and held-out PSNR (cam00, every 5th frame).

Memory: "peak" is the process's VmHWM (/proc/self/status), reset before each phase
(/proc/self/clear_refs); it counts the frame cache's memory-mapped pages that are resident (page
cache, reclaimable), so the anonymous memory's peak (RssAnon sampled every 10 ms) and its size at the
end of each phase are printed beside it.
"""
from __future__ import annotations

import argparse
import copy
import gc
import json
import multiprocessing
import os
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from step_memory import peak_rss_gb, reset_peak_rss, status_gb  # noqa: E402  (the sibling benchmark's helpers)

import numpy as np  # noqa: E402
import torch  # noqa: E402

from stg_runtime.camera import Camera  # noqa: E402
from stg_train.data import load_dataset  # noqa: E402
from stg_train.segments import plan_segments  # noqa: E402
from stg_train.trainer import Trainer, TrainConfig  # noqa: E402

SCENE_SEED = 0
FPS = 30.0


# -- 1. the capture --------------------------------------------------------------------------------
def scene_gaussians(seed: int = SCENE_SEED, count: int = 20_000):
    """means (N, 3), velocities (N, 3) (world units per second), quats, scales, opacities, colours:
    a cloud of small Gaussians around the origin (a third of them moving) inside a shell of radius 8
    of large ones (the background)."""
    rng = np.random.default_rng(seed)
    shell = count // 5
    n = count - shell
    means = np.concatenate([rng.normal(0, 0.8, (n, 3)), 8.0 * _unit(rng.normal(size=(shell, 3)))]).astype(np.float32)
    velocity = np.zeros_like(means)
    moving = rng.random(n) < 1 / 3
    velocity[:n][moving] = rng.normal(0, 0.3, (moving.sum(), 3))
    quats = rng.normal(size=(count, 4)).astype(np.float32)
    scales = np.concatenate([np.exp(rng.uniform(np.log(0.01), np.log(0.08), (n, 3))),
                             np.full((shell, 3), 0.6)]).astype(np.float32)
    opacities = np.concatenate([rng.uniform(0.3, 1.0, n), np.ones(shell)]).astype(np.float32)
    colours = rng.uniform(0, 1, (count, 3)).astype(np.float32)
    return means, velocity, quats, scales, opacities, colours


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def ring_cameras(cameras: int, width: int, height: int) -> list[Camera]:
    """cam00.. on a ring of radius 4 around the origin (a forward-facing rig's spread, 60 degrees of arc)."""
    out = []
    for i in range(cameras):
        a = np.deg2rad(-30 + 60 * i / max(cameras - 1, 1))
        eye = [4.0 * np.sin(a), 0.3 * np.sin(3 * a), -4.0 * np.cos(a)]
        out.append(Camera.look_at(eye, [0, 0, 0], [0, -1, 0], 60.0, width, height, name=f"cam{i:02d}"))
    return out


def _write_camera(job) -> tuple[float, float]:
    """Worker: draw camera `index`'s frames and write <data>/camXX.mp4; returns its (near, far)."""
    import cv2
    import numba

    from stg_runtime.splat_cpu import rasterize

    data, index, cameras, frames, width, height, draw_scale, threads = job
    numba.set_num_threads(threads)
    cam = ring_cameras(cameras, width, height)[index]
    small = cam if draw_scale == 1 else cam.resized(width // draw_scale, height // draw_scale)
    means, velocity, quats, scales, opacities, colours = scene_gaussians()
    path = Path(data) / f"{cam.name}.mp4"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), FPS, (width, height))
    if not writer.isOpened():
        raise RuntimeError(f"{path}: OpenCV cannot write mp4v video here")
    try:
        for k in range(frames):
            rgb = rasterize(means + velocity * (k / FPS), quats, scales, opacities, colours, small)[0]
            bgr = np.ascontiguousarray(np.rint(np.clip(rgb, 0, 1) * 255).astype(np.uint8)[..., ::-1])
            writer.write(bgr if small is cam else cv2.resize(bgr, (width, height), interpolation=cv2.INTER_LINEAR))
    finally:
        writer.release()
    uv, depth = cam.project(means)
    seen = (depth > 0) & np.all((uv >= 0) & (uv < [width, height]), axis=-1)
    return float(depth[seen].min()) * 0.9, float(depth[seen].max()) * 1.1


def generate(data: Path, cameras: int, frames: int, width: int, height: int, workers: int, draw_scale: int = 1) -> bool:
    """Write the capture into `data` unless one with these settings is there; True when written.
    draw_scale: frames drawn at 1/draw_scale size and enlarged (bilinear), draw_scale^2 times faster."""
    from stg_train.synthetic import llff_pose

    settings = {"generator": "bench/scale.py", "seed": SCENE_SEED, "num_cameras": cameras, "num_frames": frames,
                "width": width, "height": height, "fps": FPS, "draw_scale": draw_scale}
    meta = data / "scene.json"
    if meta.exists() and json.loads(meta.read_text()) == settings:
        return False
    data.mkdir(parents=True, exist_ok=True)
    meta.unlink(missing_ok=True)
    for old in data.glob("cam*.mp4"):  # of an earlier capture (another camera count)
        old.unlink()
    jobs = [(str(data), i, cameras, frames, width, height, draw_scale, max(1, (os.cpu_count() or 1) // workers))
            for i in range(cameras)]
    with multiprocessing.get_context("spawn").Pool(workers) as pool:
        bounds = pool.map(_write_camera, jobs, chunksize=1)
    poses = np.zeros((cameras, 17))
    for i, cam in enumerate(ring_cameras(cameras, width, height)):
        poses[i, :15] = llff_pose(cam).ravel()
        poses[i, 15:] = bounds[i]
    np.save(data / "poses_bounds.npy", poses)
    meta.write_text(json.dumps(settings))
    return True


# -- measuring -------------------------------------------------------------------------------------
def rss_anon_gb() -> float:
    """The process's anonymous resident memory now (RssAnon), in GB."""
    return status_gb("RssAnon")


class AnonymousPeak(threading.Thread):
    """The largest RssAnon seen since the last reset, sampled every `interval` seconds (a daemon thread):
    the process's own memory, without the memory-mapped frame cache's pages that VmHWM also counts."""

    def __init__(self, interval: float = 0.01):
        super().__init__(daemon=True)
        self.interval, self.peak = interval, rss_anon_gb()

    def run(self) -> None:
        while True:
            self.peak = max(self.peak, rss_anon_gb())
            time.sleep(self.interval)

    def reset(self) -> None:
        self.peak = rss_anon_gb()


ANONYMOUS = AnonymousPeak()


def reset_peaks() -> None:
    """Start both peaks (VmHWM and the sampled RssAnon) again from the current memory."""
    reset_peak_rss()
    ANONYMOUS.reset()


def disk_gb(folder: Path) -> float:
    """Bytes allocated on disk under `folder`, in GB."""
    return sum(os.stat(os.path.join(d, f)).st_blocks * 512 for d, _, files in os.walk(folder) for f in files) / 1e9


def memory(label: str) -> str:
    return (f"{label}: peak {peak_rss_gb():.2f} GB (VmHWM), anonymous peak {ANONYMOUS.peak:.2f} GB (RssAnon "
            f"sampled every 10 ms), anonymous now {rss_anon_gb():.2f} GB")


def step_seconds(trainer: Trainer, steps: int, cuda: bool = False) -> float:
    """Mean seconds of `steps` training steps after one warm-up step (kernel compilation)."""
    trainer.train_step()
    if cuda:
        torch.cuda.synchronize()
    t0 = time.perf_counter()
    for _ in range(steps):
        trainer.train_step()
    if cuda:
        torch.cuda.synchronize()
    return (time.perf_counter() - t0) / steps


def cache_folders(dataset) -> list[str]:
    """Names of the frame-cache chunk folders that exist (decoded chunks)."""
    root = dataset.frames.cache_dir
    return sorted(p.name for p in root.iterdir() if p.is_dir()) if root.is_dir() else []


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cameras", type=int, default=20)
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--width", type=int, default=1352)
    ap.add_argument("--height", type=int, default=1014)
    ap.add_argument("--data", default="/tmp/stg_scale", help="where the capture is written (and reused)")
    ap.add_argument("--workers", type=int, default=os.cpu_count(), help="processes drawing the frames")
    ap.add_argument("--draw-scale", type=int, default=1,
                    help="draw the frames at 1/N size and enlarge them (N^2 times faster generation)")
    ap.add_argument("--segment-frames", type=int, default=50)
    ap.add_argument("--gaussians", type=int, default=200_000, help="initial Gaussians (view volume)")
    ap.add_argument("--depth-candidates", type=int, default=64, help="of the view-volume initialisation")
    ap.add_argument("--steps", type=int, default=3, help="timed steps per splatter")
    ap.add_argument("--torch-downscale", type=int, default=4, help="the CPU torch splatter's size divisor")
    ap.add_argument("--whole", action=argparse.BooleanOptionalAction, default=True,
                    help="also decode every other segment (the whole video's cache)")
    ap.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda"],
                    help="auto: the GPU part runs when CUDA is available")
    ap.add_argument("--cpu", action=argparse.BooleanOptionalAction, default=True,
                    help="the CPU training steps (numba, torch); --no-cpu on a GPU machine to save time")
    ap.add_argument("--segment-iterations", type=int, default=30_000,
                    help="steps of the timed GPU segment run (the reference schedule: 30000)")
    ap.add_argument("--segment", action=argparse.BooleanOptionalAction, default=True,
                    help="the GPU segment run (time and held-out PSNR)")
    ap.add_argument("--threads", type=int, default=os.cpu_count())
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    ANONYMOUS.start()
    cuda = args.device == "cuda" or (args.device == "auto" and torch.cuda.is_available())
    data = Path(args.data)
    print(f"capture: {args.cameras} cameras x {args.frames} frames at {args.width}x{args.height} in {data}; "
          f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f}", flush=True)

    t0 = time.perf_counter()
    written = generate(data, args.cameras, args.frames, args.width, args.height, args.workers, args.draw_scale)
    videos = sum(p.stat().st_size for p in data.glob("cam*.mp4")) / 1e9
    print(f"generate: {time.perf_counter() - t0:.0f} s ({'written' if written else 'reused'}, "
          f"{args.workers} workers), videos {videos:.2f} GB", flush=True)

    reset_peaks()
    spans = [(s.start, s.count) for s in plan_segments(args.frames, args.segment_frames)]
    dataset = load_dataset(data, "n3v", from_video=True, lazy=True).chunked(spans)
    segment = dataset.frame_range(*spans[0])
    t0 = time.perf_counter()
    segment.frame(0, 0)  # decodes segment 0's chunk (or opens it)
    seconds = time.perf_counter() - t0
    frames = args.cameras * spans[0][1]
    print(f"decode segment 0 ({frames} frames): {seconds:.1f} s ({frames / seconds:.0f} frames/s), cache "
          f"{disk_gb(dataset.frames.cache_dir):.2f} GB on disk; cache folders now: {cache_folders(dataset)}",
          flush=True)
    print(memory("  memory while decoding"), flush=True)

    reset_peaks()
    t0 = time.perf_counter()
    base = TrainConfig(num_points=args.gaussians, init="volume", depth_candidates=args.depth_candidates,
                       iterations=args.segment_iterations, checkpoint_every=10**9)
    trainer = Trainer(segment, TrainConfig(**{**base.__dict__, "splatter": "numba"}))
    start = copy.deepcopy(trainer.state_dict())  # the GPU runs start from these points (no new initialisation)
    print(f"initialise segment 0 (view volume, {args.gaussians} points, {args.depth_candidates} depth candidates): "
          f"{time.perf_counter() - t0:.1f} s", flush=True)
    print(memory("  memory of the initialisation"), flush=True)

    if args.cpu:
        reset_peaks()
        s = step_seconds(trainer, args.steps)
        print(f"CPU numba splatter at {args.width}x{args.height}: {s:.2f} s/step ({trainer.params.count} Gaussians)",
              flush=True)
        print(memory("  memory of the steps"), flush=True)
        del trainer
        gc.collect()
        small = load_dataset(data, "n3v", downscale=args.torch_downscale, from_video=True, lazy=True).chunked(spans)
        small = small.frame_range(*spans[0])
        small.frame(0, 0)
        reset_peaks()
        for splatter in ("numba", "torch"):
            t = Trainer(small, TrainConfig(**{**base.__dict__, "splatter": splatter}))
            s = step_seconds(t, args.steps)
            print(f"CPU {splatter} splatter at {small.width}x{small.height}: {s:.2f} s/step", flush=True)
            print(memory(f"  memory of the {splatter} steps"), flush=True)
            del t
            gc.collect()
            reset_peaks()
    print(f"cache folders after segment 0's training: {cache_folders(dataset)}", flush=True)

    if args.whole and len(spans) > 1:
        reset_peaks()
        t0 = time.perf_counter()
        for a, n in spans[1:]:
            dataset.frames.chunk(a, n)
        frames = args.cameras * (args.frames - spans[0][1])
        seconds = time.perf_counter() - t0
        print(f"decode the other {len(spans) - 1} segments ({frames} frames): {seconds:.1f} s "
              f"({frames / seconds:.0f} frames/s); whole cache {disk_gb(dataset.frames.cache_dir):.2f} GB on disk",
              flush=True)
        print(memory("  memory while decoding"), flush=True)

    if cuda:
        gpu(segment, base, start, args)


def gpu(segment, base: TrainConfig, start: dict, args, device: str = "cuda", splatters=("gsplat", "torch")) -> None:
    """Seconds per step and GPU peak memory with each of `splatters`; the timed segment run with the
    first that ran; every run starts from the trainer state `start` (the initial points)."""
    print(f"GPU: {torch.cuda.get_device_name()}", flush=True)
    config = {**base.__dict__, "device": device}
    working = []  # the splatters that ran
    for splatter in splatters:
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats()
        reset_peaks()
        try:
            t = Trainer(segment, TrainConfig(**{**config, "splatter": splatter}), _state=copy.deepcopy(start))
            s = step_seconds(t, max(args.steps, 10), cuda=True)
            print(f"GPU {splatter} at {segment.width}x{segment.height}: {s:.3f} s/step, GPU peak "
                  f"{torch.cuda.max_memory_allocated() / 1e9:.2f} GB allocated "
                  f"({torch.cuda.max_memory_reserved() / 1e9:.2f} GB reserved)", flush=True)
            print(memory("  host memory"), flush=True)
            working.append(splatter)
        except Exception as e:  # noqa: BLE001  (gsplat missing, out of memory: say so, go on)
            print(f"GPU {splatter}: failed ({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''})",
                  flush=True)
        t = None
    if not args.segment or not working:
        return
    torch.cuda.empty_cache()
    torch.cuda.reset_peak_memory_stats()
    reset_peaks()
    t0 = time.perf_counter()
    trainer = Trainer(segment, TrainConfig(**{**config, "splatter": working[0]}), _state=copy.deepcopy(start))
    setup = time.perf_counter() - t0
    trainer.train(progress=False)
    torch.cuda.synchronize()
    train = time.perf_counter() - t0 - setup
    frames = range(0, segment.num_frames, 5)
    psnr = trainer.heldout_psnr(frames)
    print(f"GPU segment 0, {working[0]}, {args.segment_iterations} steps: set-up {setup:.0f} s, training "
          f"{train:.0f} s ({train / args.segment_iterations:.3f} s/step), {trainer.params.count} Gaussians, "
          f"held-out PSNR {psnr:.2f} dB (cam00, frames {list(frames)}); GPU peak "
          f"{torch.cuda.max_memory_allocated() / 1e9:.2f} GB", flush=True)
    print(memory("  host memory"), flush=True)


if __name__ == "__main__":
    main()
