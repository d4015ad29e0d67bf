#!/usr/bin/env python
"""stg-prep on the synthetic scene, its poses thrown away: the seconds of each stage, the offsets found
and the pose errors, for rigs of 12 and 20 cameras (docs/datasets.md, "Your own videos").

    python bench/prep.py [--cameras 12,20] [--size 640x480] [--frames 30] [--data DIR] [--threads N]
                         [--scene-seed S] [--train] [--seeds 0,1] [--iterations N] [--downscale K]
                         [--world prepared|truth] [--reuse]

For each camera count the scene (stg_train.synthetic, `stg-synth --cameras C`) is written in the N3V
layout into DATA/n3v_C_WxH_F/ (reused when there; --scene-seed S other than 0 draws another scene and
rig, and every folder's name then ends in _sceneS), and from it a folder of raw videos: each camera's
lossless frames, its first 0-5 frames left out (a camera that started late, drawn from seed 0),
poses_bounds.npy dropped. stg_train.prep.prepare turns that into DATA/prep_C/; the table gives each
stage's seconds, the cameras registered, whether every offset came back exactly, and the largest
rotation and position errors after one similarity to the truth (stg_train.rig.gauge.aligned_pose_errors;
positions in % of the rig's largest distance between cameras).

--train (expensive: four trainings per camera count) trains DATA/prep_C/ and DATA/true_C/, the same
frames and 3D points with the true cameras (moved into the prepared world by one similarity, so that
only the calibration's errors differ; --world truth moves the points into the truth's world instead),
with stg-train's defaults for each seed, and evaluates each with `stg-eval --align-poses` on its held-out cam00; it
prints both PSNRs and their difference. --downscale K trains and evaluates both at 1/K of the frames'
size (the calibration still sees them whole).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from machine import describe  # noqa: E402

from stg_runtime.progress import progress_stages  # noqa: E402
from stg_train.prep import prepare  # noqa: E402
from stg_train.rig.gauge import aligned_pose_errors  # noqa: E402
from stg_train.synthetic import SyntheticScene, write_n3v  # noqa: E402


def raw_videos(n3v: Path, out: Path, cuts) -> None:
    """out/<camera>/<k>.png: camera c's frames from cuts[c] on."""
    shutil.rmtree(out, ignore_errors=True)
    for folder, cut in zip(sorted((n3v / "frames").iterdir()), cuts):
        (out / folder.name).mkdir(parents=True)
        for k, f in enumerate(sorted(folder.glob("*.png"))[cut:]):
            os.link(f, out / folder.name / f"{k}.png")


def errors(prepared: Path, truth) -> tuple[float, float]:
    """(largest rotation error, degrees; largest position error, % of the rig's size) of prepared/."""
    from stg_train.data import load_dataset

    cams = load_dataset(prepared, lazy=True).cameras
    rotation, position = aligned_pose_errors(np.stack([c.world_to_camera for c in cams]),
                                             np.stack([c.world_to_camera for c in truth]))
    centres = np.stack([-c.world_to_camera[:3, :3].T @ c.world_to_camera[:3, 3] for c in truth])
    size = max(np.linalg.norm(a - b) for a in centres for b in centres)
    return float(rotation.max()), float(100 * position.max() / size)


def true_rig(prepared: Path, out: Path, truth, world: str = "prepared") -> None:
    """out/: prepared/'s frames (hard links) and 3D points with the true cameras. world "prepared": the
    true cameras moved into the prepared world (by the inverse of the similarity that takes the prepared
    cameras onto the true ones), so the two runs differ by the calibration's errors alone; "truth": the
    points moved into the truth's world instead (the world's axes and scale then differ too)."""
    import pycolmap

    from stg_train.data import load_dataset
    from stg_train.data.colmap import read_reconstruction, reconstruction_from_cameras, write_reconstruction
    from stg_train.data.colmap import reconstruction_points
    from stg_train.rig.gauge import similarity_between

    cams = load_dataset(prepared, lazy=True).cameras
    scale, rotation, shift = similarity_between(np.stack([c.world_to_camera for c in cams]),
                                                np.stack([c.world_to_camera for c in truth]))
    shutil.rmtree(out, ignore_errors=True)
    shutil.copytree(prepared / "images", out / "images", copy_function=os.link)
    xyz, rgb = reconstruction_points(read_reconstruction(prepared / "sparse" / "0"))
    if world == "prepared":  # x_truth = s R x + t: the true camera [Rc | tc] is [Rc R | (Rc t + tc) / s] here
        truth = [replace(c, world_to_camera=_moved(c.world_to_camera, scale, rotation, shift)) for c in truth]
    else:
        xyz = scale * xyz @ rotation.T + shift
    rec = reconstruction_from_cameras(list(truth))
    for p, c in zip(xyz, np.round(rgb * 255).astype(np.uint8)):
        rec.add_point3D(p, pycolmap.Track(), c)
    write_reconstruction(rec, out / "sparse" / "0")


def _moved(w2c: np.ndarray, scale: float, rotation: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """A world-to-camera (4, 4) of the world x_truth = scale rotation x + shift, in the world of x."""
    out = np.eye(4)
    out[:3, :3] = w2c[:3, :3] @ rotation
    out[:3, 3] = (w2c[:3, :3] @ shift + w2c[:3, 3]) / scale
    return out


def held_out_psnr(data: Path, out: Path, seed: int, iterations: int | None, downscale: int,
                  reuse: bool = False) -> float:
    """PSNR on cam00 (held out) of stg-train's defaults on data, by stg-eval --align-poses; with `reuse`,
    that of an earlier run into `out` where it has one."""
    report = out / "eval.json"
    if reuse and report.is_file():
        return float(json.loads(report.read_text())["psnr"])
    scale = ["--downscale", str(downscale)]
    train = ["stg-train", str(data), "--out", str(out), "--seed", str(seed), "--quiet", "--force", *scale]
    if iterations:
        train += ["--iterations", str(iterations)]
    subprocess.run(train, check=True, stdout=subprocess.DEVNULL)
    subprocess.run(["stg-eval", str(out / "model.stg"), str(data), "--align-poses", "--json", str(report), *scale],
                   check=True, stdout=subprocess.DEVNULL)
    return float(json.loads(report.read_text())["psnr"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cameras", default="12,20")
    ap.add_argument("--size", default="640x480")
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--data", default=os.path.join("/tmp", "stg-bench-prep"))
    ap.add_argument("--scene-seed", type=int, default=0, help="stg-synth's scene and rig (default 0)")
    ap.add_argument("--threads", type=int, default=-1, help="pycolmap's threads (default: all)")
    ap.add_argument("--train", action="store_true", help="also train both ways and compare (expensive)")
    ap.add_argument("--seeds", default="0,1")
    ap.add_argument("--iterations", type=int, default=None, help="training steps (default stg-train's)")
    ap.add_argument("--downscale", type=int, default=1, help="train and evaluate at 1/K of the size")
    ap.add_argument("--world", choices=("prepared", "truth"), default="prepared",
                    help="the true-pose run's world: the prepared one (only the poses differ) or the truth's")
    ap.add_argument("--reuse", action="store_true", help="reuse the preparation and the runs already evaluated in DATA")
    args = ap.parse_args()
    width, height = map(int, args.size.split("x"))
    data = Path(args.data)
    print(describe())
    print(f"synthetic scene, {width}x{height}, {args.frames} frames, starts cut 0-5 frames, PNG frame folders")
    rows = []
    for count in map(int, args.cameras.split(",")):
        tag = f"_scene{args.scene_seed}" if args.scene_seed else ""
        n3v = data / f"n3v_{count}_{width}x{height}_{args.frames}{tag}"
        scene = SyntheticScene(seed=args.scene_seed, duration=args.frames / 30.0)
        if not (n3v / "poses_bounds.npy").is_file():
            write_n3v(n3v, scene, num_cameras=count, num_frames=args.frames, width=width, height=height)
        truth = scene.cameras(count, width, height)
        cuts = np.random.default_rng(0).integers(0, 6, count)
        prep_dir, raw_dir = data / f"prep_{count}{tag}", data / f"raw_{count}{tag}"
        done = prep_dir / "prep.json"
        if args.reuse and done.is_file():  # the runs reused were trained on this calibration
            report = json.loads(done.read_text())
        else:
            raw_videos(n3v, raw_dir, cuts)
            with progress_stages() as stage:
                report = prepare(raw_dir, prep_dir, force=True, threads=args.threads, progress=stage)
        exact = [c["offset"] for c in report["cameras"]] == [int(max(cuts) - c) for c in cuts]
        rotation, position = errors(prep_dir, truth)
        rows.append((count, report, exact, rotation, position))
        if args.train:
            name = f"true_{count}{tag}" + ("" if args.world == "prepared" else "_truthworld")
            true_rig(prep_dir, data / name, truth, args.world)
            for seed in map(int, args.seeds.split(",")):
                runs = data / "runs"
                prepared = held_out_psnr(prep_dir, runs / f"{prep_dir.name}_s{seed}", seed, args.iterations,
                                         args.downscale, args.reuse)
                true = held_out_psnr(data / name, runs / f"{name}_s{seed}", seed, args.iterations, args.downscale,
                                     args.reuse)
                print(f"{count} cameras, seed {seed}: held-out cam00 {prepared:.2f} dB prepared, {true:.2f} dB "
                      f"true poses, difference {prepared - true:+.2f} dB")
    stages = ("check", "read", "sync", "calibrate", "write")
    print(f"{'cameras':>7} " + " ".join(f"{s:>9}" for s in stages) + f" {'total':>7} {'registered':>10} "
          f"{'offsets':>8} {'rot max':>8} {'pos max':>8}")
    for count, report, exact, rotation, position in rows:
        sec = report["seconds"]
        print(f"{count:>7} " + " ".join(f"{sec[s]:>8.1f}s" for s in stages) + f" {sum(sec.values()):>6.1f}s "
              f"{report['calibration']['registered']:>4}/{count:<5} {'exact' if exact else 'WRONG':>8} "
              f"{rotation:>7.3f}d {position:>7.2f}%")


if __name__ == "__main__":
    main()
