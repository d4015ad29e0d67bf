#!/usr/bin/env python
"""One synthetic room in two layouts, trained from each initialisation: held-out and novel-view PSNR,
Gaussian count and file size (docs/notes/initial-points.md, "Custom captures").

    python bench/init_layouts.py --variants n3v-volume,rig-sfm,rig-combined,rig-volume [--iterations 500]
                                 [--data DIR] [--out DIR] [--splatter torch] [--init-every N]

The scene (stg_train.synthetic, 12 cameras x 30 frames at 160x120 unless --cameras/--frames/--size) is
written once into DIR/n3v (the N3V layout, as stg-synth writes it) and copied into DIR/rig: the same
lossless PNG frames as images/<camera>/<frame>.png plus a COLMAP model of the rig in sparse/0 with the
cameras only (no 3D points), what a user of the rig layout brings. Both layouts are read from their
lossless frames, so the two differ only in what the layout stores: N3V's near/far depth bounds.

A variant is <layout>-<init>: layout n3v or rig, init any of stg-train's --init choices. Each trains with
stg_train.pipeline.train (the default settings, --iterations steps) into OUT/<variant>/, and is then
evaluated with the runtime Player on the held-out camera cam00 (every frame) and on three novel cameras
whose ground truth is ray traced (every 3rd frame): "between" halfway between cam01 and cam02 (inside
the rig), "outside" the next position of a larger rig (just beyond the training cameras), "closer" cam00
moved 0.5 units towards the scene. Figures go to OUT/<variant>/bench.json and a table is printed.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
from pathlib import Path

import stg_train  # noqa: F401  (first: it configures OpenMP before torch loads)
import numpy as np

from stg_runtime.camera import Camera
from stg_runtime.player import Player
from stg_train.data import load_dataset
from stg_train.data.colmap import reconstruction_from_cameras, write_reconstruction
from stg_train.metrics import psnr
from stg_train.pipeline import train
from stg_train.synthetic import SyntheticScene, write_n3v
from stg_train.trainer import TrainConfig

NOVEL = ("between", "outside", "closer")


def write_scenes(data: Path, cameras: int, frames: int, fps: float, size: tuple[int, int]) -> SyntheticScene:
    """DIR/n3v and DIR/rig of the same scene (written once; reused when present)."""
    scene = SyntheticScene(seed=0, duration=frames / fps)
    n3v, rig = data / "n3v", data / "rig"
    if not (n3v / "scene.json").is_file():
        write_n3v(n3v, scene, num_cameras=cameras, num_frames=frames, fps=fps, width=size[0], height=size[1])
    if not (rig / "sparse" / "0" / "cameras.bin").is_file():
        cams = scene.cameras(cameras, *size)
        for cam in cams:
            folder = rig / "images" / cam.name
            folder.mkdir(parents=True, exist_ok=True)
            for png in sorted((n3v / "frames" / cam.name).glob("*.png")):
                shutil.copyfile(png, folder / png.name)
        write_reconstruction(reconstruction_from_cameras(cams), rig / "sparse" / "0")
    return scene


def novel_cameras(scene: SyntheticScene, cameras: int, size: tuple[int, int]) -> dict[str, Camera]:
    """The three novel views of the module docstring."""
    cams = scene.cameras(cameras + 1, *size)
    a, b = cams[1], cams[2]
    centre = (a.center + b.center) / 2
    forward = a.R[2] + b.R[2]
    forward /= np.linalg.norm(forward)
    right = np.cross([0.0, 1.0, 0.0], forward)
    right /= np.linalg.norm(right)
    R = np.stack([right, np.cross(forward, right), forward])
    between = np.eye(4)
    between[:3, :3], between[:3, 3] = R, -R @ centre
    closer = cams[0].world_to_camera.copy()
    closer[:3, 3] -= cams[0].R @ (cams[0].R[2] * 0.5)  # centre moved 0.5 along the viewing direction
    c0 = cams[0]
    make = lambda w2c, name: Camera(c0.fx, c0.fy, c0.cx, c0.cy, c0.width, c0.height, w2c, name)  # noqa: E731
    return {"between": make(between, "between"), "outside": cams[cameras], "closer": make(closer, "closer")}


def novel_psnr(model: Path, scene: SyntheticScene, cams: dict[str, Camera], frames: int, fps: float) -> dict:
    """Mean PSNR (dB) of the model against the ray-traced scene, per novel camera, every 3rd frame."""
    player = Player(model, device="cpu")
    out = {}
    for name, cam in cams.items():
        values = []
        for j in range(0, frames, 3):
            truth = np.rint(scene.render(cam, j / fps) * 255) / 255
            values.append(psnr(player.render(cam, j / fps), truth))
        out[name] = float(np.mean(values))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--variants", default="n3v-volume,rig-sfm,rig-combined,rig-volume")
    ap.add_argument("--iterations", type=int, default=500)
    ap.add_argument("--points", type=int, default=None, help="initial points (default: TrainConfig's)")
    ap.add_argument("--init-every", type=int, default=1)
    ap.add_argument("--splatter", default="torch", help="as stg-train --splatter (default torch, as the docs' figures)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--cameras", type=int, default=12)
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--fps", type=float, default=30.0)
    ap.add_argument("--size", default="160x120")
    ap.add_argument("--data", default=os.path.join("/tmp", "stg-init-layouts"))
    ap.add_argument("--out", default=os.path.join("/tmp", "stg-init-layouts", "runs"))
    args = ap.parse_args()
    import torch

    torch.set_num_threads(args.threads)
    size = tuple(int(v) for v in args.size.lower().split("x"))
    data, out = Path(args.data), Path(args.out)
    scene = write_scenes(data, args.cameras, args.frames, args.fps, size)
    cams = novel_cameras(scene, args.cameras, size)
    rows = []
    for variant in args.variants.split(","):
        layout, init = variant.split("-", 1)
        dataset = load_dataset(data / layout, layout=layout, show_progress=False)
        config = TrainConfig(iterations=args.iterations, init=init, init_every=args.init_every,
                             splatter=args.splatter)
        if args.points:
            config.num_points = args.points
        print(f"== {variant}: {dataset}; {config.iterations} steps, {config.splatter} splatter", flush=True)
        metrics = train(dataset, out / variant, config, quiet=True, lpips={})
        novel = novel_psnr(out / variant / "model.stg", scene, cams, args.frames, args.fps)
        row = {"variant": variant, "heldout_psnr": metrics["heldout"]["psnr"], **{f"novel_{k}": v for k, v in novel.items()},
               "gaussians": metrics["gaussians"], "file_bytes": metrics["file_bytes"],
               "train_seconds": metrics["train_seconds"], "init": metrics.get("init")}
        (out / variant / "bench.json").write_text(json.dumps(row, indent=1) + "\n")
        rows.append(row)
        print(json.dumps(row), flush=True)
    print(f"\n{'variant':<16} {'held-out':>9} " + " ".join(f"{n:>9}" for n in NOVEL) + f" {'Gaussians':>9} {'MB':>6}")
    for r in rows:
        print(f"{r['variant']:<16} {r['heldout_psnr']:9.2f} " + " ".join(f"{r['novel_' + n]:9.2f}" for n in NOVEL)
              + f" {r['gaussians']:9d} {r['file_bytes'] / 1e6:6.2f}")
    print(f"(dB; held-out: cam00, every frame; novel: every 3rd frame; {args.iterations} steps)", file=sys.stderr)


if __name__ == "__main__":
    main()
