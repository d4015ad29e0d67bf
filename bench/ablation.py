#!/usr/bin/env python
"""Ablation of the paper's Table 4 on the default synthetic scene: the full model, then each component
switched off, trained with the same settings and seed; prints held-out PSNR (whole image, and apart for
the dynamic and the static pixels), DSSIM1, Gaussians and training time per variant beside the full
model, the same dynamic / static PSNR at two novel views inside the rig (ground truth ray traced), and
where the held-out camera's dynamic error is: PSNR and share of the squared error of its dynamic pixels
by the object they show (the room, where objects pass or cast shadows; the moving sphere; ...).

    python bench/ablation.py [--iterations N] [--points N] [--cameras C] [--frames F] [--width W]
                             [--height H] [--supersample S] [--variants full,no-motion,...]
                             [--set KEY=VALUE ...] [--true-motion] [--videos] [--per-frame 0,10,20]
                             [--no-novel] [--threads 2] [--json PATH]

Variants (TrainConfig settings): full; no-temporal-opacity (frozen temporal_opacity: opacity(t) = 1);
no-motion (frozen motion = 0); no-rotation (frozen omega = 0); no-feature-splatting (the lite model:
splatted base rgb, no view / time features, no decoder); no-guided (guided=False). --set changes a
TrainConfig field for every variant (VALUE is JSON, else a string: --set splatter=numba,
--set 'schedule={"densify_until": 600}'), which makes this the screening tool of docs/notes/dynamic.md.
Defaults are the demo's (stg_train.pipeline DEMO_SCENE / DEMO_TRAINING: 12 cameras x 30 frames at
160x120, 1500 iterations, 8000 initial points), about 15-20 min per variant on 2 idle CPU cores;
`--iterations 500 --points 4000` took 11-16 min per variant on 2 cores shared with other jobs. Held-out
figures use the trainer's renderer on the held-out camera at every frame against the lossless PNG
frames (PSNR in dB; DSSIM1 = (1 - SSIM) / 2, scikit-image SSIM, data_range 1; dynamic pixels:
stg_train.metrics.dynamic_mask at its default threshold, per camera over the clip). Guided sampling only
acts on views whose SSIM is below 0.91 at its start: with a sparse initialisation (e.g. `--points 300
--variants full,no-guided`) it matters, with a dense one it may not. --supersample 4 renders the scene's
ground truth (and the novel views') with 4 x 4 rays per pixel: the demo's one ray per pixel leaves the
checkered objects aliased, which no 3D model can reproduce (docs/dynamic.md). --true-motion (a
diagnostic) gives the Gaussians initialised on the moving sphere its true trajectory as their motion.
--videos trains from the scene's lossy videos (camXX.mp4), as a user's capture would be, instead of its
PNG frames; the figures are still against the lossless frames. --per-frame J,... adds a per-frame
reference: for each frame J, a model trained on that frame alone (the training cameras at J, the full
model's settings and step count), and the held-out camera's PSNR at J over the clip's dynamic and
static pixels, for it and for every variant (docs/dynamic.md, "A per-frame reference").
"""
from __future__ import annotations

import argparse
import json
import os
import tempfile
from pathlib import Path

import stg_train  # noqa: F401  (first: it configures OpenMP before torch loads)
import numpy as np
import torch

from stg_train.pipeline import DEMO_SCENE, DEMO_TRAINING, ensure_demo_scene
from stg_train.data import load_n3v
from stg_train.data.dataset import Dataset
from stg_train.metrics import dynamic_mask, evaluate_images, psnr_of_mse
from stg_train.synthetic import OBJECT_NAMES, SyntheticScene, novel_view_dataset
from stg_train.trainer import Trainer, TrainConfig

#: name -> (table label, TrainConfig overrides)
VARIANTS = {
    "full": ("Ours full", {}),
    "no-temporal-opacity": ("w/o temporal opacity", {"frozen": ("temporal_opacity",)}),
    "no-motion": ("w/o polynomial motion", {"frozen": ("motion",)}),
    "no-rotation": ("w/o polynomial rotation", {"frozen": ("rotation",)}),
    "no-feature-splatting": ("w/o feature splatting (lite rgb)", {"model": "lite"}),
    "no-guided": ("w/o guided sampling", {"guided": False}),
    # the deviations from the reference implementation (docs/training.md): each flips one default
    "stat-summed": ("statistic: batch's vectors summed (old)", {"thresholds": {"grad_statistic": "summed"}}),
    "prune-reference": ("no prune at densification (reference)", {"thresholds": {"prune_at_densify": False}}),
    "guided-reference": ("guided: depthmax, >= 2 views (reference)",
                         {"guided_settings": {"depth": "max", "min_views": 2}}),
    "separate-rotation": ("omega kept for movers only (reference)", {"separate_rotation": True}),
    "scale-lr-reference": ("scale lr 0.003 (reference N3V)", {"learning_rates": {"log_scale": 0.003}}),
    "sfm-init": ("SfM initial points (reference)", {"init": "sfm"}),
    "zero-motion": ("zero initial motion (reference)", {"motion_init": "zero"}),
    "unstretched-rates": ("30k-step velocity rates (reference)", {"stretch_rates": False}),
    "t-center-random": ("new Gaussians' temporal centres random (reference)",
                        {"thresholds": {"new_t_center": "random"}}),
    "t-center-mean": ("new Gaussians' temporal centres at the mean hot time (before 2026-12-04)",
                      {"thresholds": {"new_t_center": "gradient"}}),
}
#: The paper's Table 4 (the default variants).
TABLE4 = ("full", "no-temporal-opacity", "no-motion", "no-rotation", "no-feature-splatting", "no-guided")
#: The rows of docs/training.md's table of deviations from the reference (bench/ablation.py --deviations).
DEVIATIONS = ("full", "stat-summed", "prune-reference", "guided-reference", "separate-rotation", "scale-lr-reference",
              "sfm-init", "zero-motion", "unstretched-rates", "t-center-random", "t-center-mean")


FIGURES = ("psnr", "dssim1", "dynamic_psnr", "static_psnr", "dynamic_ssim", "static_ssim", "dynamic_fraction")


def evaluate(trainer: Trainer, dataset) -> dict:
    """FIGURES: means over the test cameras of `dataset` at every frame (trainer's renderer, time
    j / num_frames as in training), dynamic and static regions per camera (metrics.evaluate_images)."""
    r = evaluate_images(lambda ci, j: trainer.render_numpy(dataset.cameras[ci], j / dataset.num_frames), dataset)
    return {k: r[k] for k in FIGURES}


def frame_figures(image: np.ndarray, dataset, frame: int) -> dict:
    """PSNR (dB) of `image` (H, W, 3) against `dataset`'s first test camera at `frame`, over the pixels
    that are dynamic over the clip (dynamic_mask) and over the others."""
    ci = dataset.test_cameras[0]
    dynamic = dynamic_mask([dataset.image(ci, j) for j in range(dataset.num_frames)])
    err = ((image - dataset.image(ci, frame)) ** 2).mean(-1)
    psnr = lambda m: psnr_of_mse(max(err[m].mean(), 1e-12)) if m.any() else None  # noqa: E731
    return {"dynamic_psnr": psnr(dynamic), "static_psnr": psnr(~dynamic)}


def per_frame_reference(train_ds, eval_ds, config: TrainConfig, frame: int) -> dict:
    """frame_figures of a model trained with `config` on `train_ds`'s frame `frame` alone (every camera
    at that frame, as a one-frame dataset), against `eval_ds` at that frame."""
    frames = np.stack([train_ds.frame(ci, frame)[None] for ci in range(len(train_ds.cameras))])
    one = Dataset(train_ds.cameras, frames, train_ds.fps, test_cameras=train_ds.test_cameras,
                  bounds=train_ds.bounds)
    trainer = Trainer(one, config)
    trainer.train(progress=False)
    return frame_figures(trainer.render_numpy(eval_ds.cameras[eval_ds.test_cameras[0]], 0.0), eval_ds, frame)


def object_breakdown(trainer: Trainer, dataset, scene: SyntheticScene) -> dict:
    """Where the dynamic error is: PSNR (dB) over the dynamic pixels of `dataset`'s first test camera
    (its dynamic_mask over the clip) that show each object at their frame (SyntheticScene.object_ids
    at time j / fps; "room" for the walls, floor and ceiling, which are dynamic where objects pass
    or cast shadows), and that object's share of the dynamic pixels' squared error."""
    ci = dataset.test_cameras[0]
    frames = range(dataset.num_frames)
    truth = [dataset.image(ci, j) for j in frames]
    dynamic = dynamic_mask(truth)
    err = np.stack([((trainer.render_numpy(dataset.cameras[ci], j / dataset.num_frames) - truth[j]) ** 2).mean(-1)
                    for j in frames])
    ids = np.stack([scene.object_ids(dataset.cameras[ci], j / dataset.fps) for j in frames])
    total = err[:, dynamic].sum()
    out = {}
    for k in np.unique(ids):
        m = (ids == k) & dynamic[None]
        if m.any():
            name = OBJECT_NAMES[k] if k >= 0 else "room"
            out[name] = {"psnr": psnr_of_mse(max(err[m].mean(), 1e-12)),
                         "share": float(err[m].sum() / max(total, 1e-12)), "pixels": int(m.sum())}
    return out


def give_true_motion(trainer: Trainer, scene: SyntheticScene, duration: float, radius: float = 0.4) -> int:
    """Diagnostic: the initial Gaussians within `radius` of the moving sphere's centre at their temporal
    centre c get its true trajectory as their motion: the least-squares cubic a dt + b dt^2 + c dt^3
    through its centre's offsets at dt in [-0.5, 0.5] (normalised time; `duration` seconds per unit).
    What the dynamic pixels gain then shows what learning the sphere's motion can be worth. Returns how
    many Gaussians were given it."""
    raw = trainer.params.raw
    centres = raw["t_center"].detach().reshape(-1).cpu().numpy()
    xyz = raw["xyz"].detach().cpu().numpy()
    dts = np.linspace(-0.5, 0.5, 41)
    basis = np.stack([dts, dts ** 2, dts ** 3], axis=1)
    path = lambda tau: scene.moving_sphere_center(tau * duration)  # noqa: E731
    given = 0
    with torch.no_grad():
        for i, c in enumerate(centres):
            if np.linalg.norm(xyz[i] - path(c)) < radius:
                offsets = np.stack([path(c + d) for d in dts]) - path(c)
                coef = np.linalg.lstsq(basis, offsets, rcond=None)[0]  # (3 powers, xyz)
                raw["motion"][i] = torch.as_tensor(coef.reshape(-1), dtype=raw["motion"].dtype)
                given += 1
    return given


def parse_setting(text: str) -> tuple[str, object]:
    """KEY=VALUE with VALUE as JSON when it parses, else the string."""
    key, sep, value = text.partition("=")
    if not sep:
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE, got {text!r}")
    try:
        return key, json.loads(value)
    except json.JSONDecodeError:
        return key, value


def _fmt(x, spec=".2f") -> str:
    return "-" if x is None else format(x, spec)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    d = DEMO_SCENE
    ap.add_argument("--iterations", type=int, default=DEMO_TRAINING["iterations"])
    ap.add_argument("--points", type=int, default=DEMO_TRAINING["num_points"])
    ap.add_argument("--cameras", type=int, default=d["cameras"])
    ap.add_argument("--frames", type=int, default=d["frames"])
    ap.add_argument("--width", type=int, default=d["width"])
    ap.add_argument("--height", type=int, default=d["height"])
    ap.add_argument("--variants", default=",".join(TABLE4), help="comma-separated subset of: " + ", ".join(VARIANTS))
    ap.add_argument("--deviations", action="store_true",
                    help="the variants of docs/training.md's deviations from the reference: " + ", ".join(DEVIATIONS))
    ap.add_argument("--set", type=parse_setting, action="append", default=[], metavar="KEY=VALUE",
                    help="a TrainConfig field for every variant (VALUE as JSON, else a string)")
    ap.add_argument("--no-novel", action="store_true", help="skip the two novel views inside the rig")
    ap.add_argument("--supersample", type=int, default=1,
                    help="rays per pixel side of the scene's ground truth (1, the demo's, is aliased where "
                         "textures are finer than a pixel)")
    ap.add_argument("--true-motion", action="store_true",
                    help="diagnostic: give the Gaussians initialised on the moving sphere its true trajectory")
    ap.add_argument("--videos", action="store_true", help="train from the lossy videos, not the PNG frames")
    ap.add_argument("--per-frame", default="", metavar="J,...",
                    help="frames at which to train a one-frame reference and compare every variant with it")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0, help="training seed")
    ap.add_argument("--scene-seed", type=int, default=0, help="the synthetic scene's seed (textures, colours)")
    ap.add_argument("--layout", type=int, default=0,
                    help="the synthetic scene's object set (stg_train.synthetic.LAYOUTS; 1: the second scene "
                         "of docs/training.md's deviations table)")
    ap.add_argument("--data", default=None, help="scene folder (generated once; default: a temp folder per size)")
    ap.add_argument("--json", default=None, help="also write the table as JSON here")
    args = ap.parse_args()
    names = list(DEVIATIONS) if args.deviations else [n.strip() for n in args.variants.split(",") if n.strip()]
    unknown = [n for n in names if n not in VARIANTS]
    if unknown:
        ap.error(f"unknown variant(s) {unknown}; choose from {list(VARIANTS)}")
    torch.set_num_threads(args.threads)
    size = f"{args.cameras}x{args.frames}-{args.width}x{args.height}"
    if args.supersample > 1:
        size += f"-ss{args.supersample}"
    if args.scene_seed or args.layout:
        size += f"-seed{args.scene_seed}-layout{args.layout}"
    data = Path(args.data or os.path.join(tempfile.gettempdir(), f"stg-ablation-scene-{size}"))
    ensure_demo_scene(data, cameras=args.cameras, frames=args.frames, width=args.width, height=args.height,
                      supersample=args.supersample, seed=args.scene_seed, layout=args.layout)
    ds = load_n3v(data, prefer_png=True)  # the lossless frames: the ground truth of every figure
    train_ds = load_n3v(data, prefer_png=False) if args.videos else ds
    settings = dict(args.set)
    scene = SyntheticScene(seed=args.scene_seed, duration=args.frames / ds.fps, layout=args.layout)
    novel = None if args.no_novel else novel_view_dataset(scene, args.frames, ds.fps, args.width, args.height,
                                                          supersample=args.supersample)
    print(f"{train_ds}; {args.iterations} iterations, {args.points} initial points, seed {args.seed}, "
          f"{args.threads} threads, settings {settings}", flush=True)

    per_frame = [int(j) for j in args.per_frame.split(",") if j.strip()]
    if any(not 0 <= j < ds.num_frames for j in per_frame):
        ap.error(f"--per-frame: frames are 0..{ds.num_frames - 1}")
    results = {}
    for name in names:
        label, overrides = VARIANTS[name]
        cfg = TrainConfig(**{**DEMO_TRAINING, "iterations": args.iterations, "num_points": args.points,
                             "seed": args.seed, **settings, **overrides})
        trainer = Trainer(train_ds, cfg)
        if args.true_motion:
            print(f"  {give_true_motion(trainer, scene, args.frames / ds.fps)} Gaussians given the moving sphere's "
                  "true trajectory", flush=True)
        trainer.train(progress=False)
        guided = next((s for s in trainer.strategies if hasattr(s, "chosen")), None)
        added = sum(e["added"] for e in guided.log) if guided is not None else 0
        results[name] = {"label": label, **evaluate(trainer, ds),
                         "novel": None if novel is None else evaluate(trainer, novel), "gaussians": trainer.params.count,
                         "objects": object_breakdown(trainer, ds, scene),
                         "train_seconds": trainer.seconds, "guided_added": added,
                         "guided_log": [] if guided is None else guided.log,
                         "guided_view_ssim": [] if guided is None else guided.scores,
                         "per_frame": {j: frame_figures(trainer.render_numpy(ds.cameras[ds.test_cameras[0]],
                                                                             j / ds.num_frames), ds, j)
                                       for j in per_frame}}
        r = results[name]
        novel_text = "" if novel is None else (f"  novel dynamic / static {_fmt(r['novel']['dynamic_psnr'])} / "
                                               f"{_fmt(r['novel']['static_psnr'])} dB")
        print(f"  {label:<34} {r['psnr']:6.2f} dB  dynamic / static {_fmt(r['dynamic_psnr'])} / "
              f"{_fmt(r['static_psnr'])} dB{novel_text}  DSSIM1 {r['dssim1']:.4f}  {r['gaussians']:6d} Gaussians  "
              f"{r['train_seconds']:6.0f} s  (guided added {added})", flush=True)
        print("    held-out dynamic pixels by object (PSNR, share of their squared error): " + ", ".join(
            f"{k} {v['psnr']:.2f} dB {100 * v['share']:.0f}%" for k, v in r["objects"].items()), flush=True)
        if guided is not None and guided.scores:
            print(f"    training-view SSIM at guided_start {trainer.schedule.guided_start}: lowest "
                  f"{guided.scores[0][0]:.3f}, highest {guided.scores[-1][0]:.3f}; sampling: {guided.log}", flush=True)

    full = results.get("full")
    header = (f"| {'Method':<34} | PSNR (dB) | vs full | dynamic | vs full | static | novel dynamic | novel static "
              f"| DSSIM1 | Gaussians | train s | guided added |")
    lines = [header, "|" + "|".join("-" * (len(c)) for c in header.split("|")[1:-1]) + "|"]
    for name, r in results.items():
        def delta(key):
            if full is None or name == "full" or r[key] is None or full[key] is None:
                return ""
            return f"{r[key] - full[key]:+.2f}"
        nv = r["novel"] or {}
        lines.append(f"| {r['label']:<34} | {r['psnr']:9.2f} | {delta('psnr'):>7} | {_fmt(r['dynamic_psnr']):>7} | "
                     f"{delta('dynamic_psnr'):>7} | {_fmt(r['static_psnr']):>6} | {_fmt(nv.get('dynamic_psnr')):>13} | "
                     f"{_fmt(nv.get('static_psnr')):>12} | {r['dssim1']:.4f} | {r['gaussians']:9d} | "
                     f"{r['train_seconds']:7.0f} | {r['guided_added']:12d} |")
    print("\n".join(lines))
    references = {}
    if per_frame:
        cfg = TrainConfig(**{**DEMO_TRAINING, "iterations": args.iterations, "num_points": args.points,
                             "seed": args.seed, **settings})
        print("\nper-frame reference: held-out dynamic / static PSNR (dB) at each frame; a variant's "
              "dynamic pixels behind the one-frame model's")
        for j in per_frame:
            ref = references[j] = per_frame_reference(train_ds, ds, cfg, j)
            cells = [f"one-frame model {_fmt(ref['dynamic_psnr'])} / {_fmt(ref['static_psnr'])}"]
            for r in results.values():
                f = r["per_frame"][j]
                behind = ("" if None in (f["dynamic_psnr"], ref["dynamic_psnr"])
                          else f", {ref['dynamic_psnr'] - f['dynamic_psnr']:.2f} behind")
                cells.append(f"{r['label']} {_fmt(f['dynamic_psnr'])} / {_fmt(f['static_psnr'])}{behind}")
            print(f"  frame {j}: " + "; ".join(cells), flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps({"settings": {**vars(args), "set": settings}, "results": results,
                                               "per_frame_reference": references}, indent=1) + "\n")


if __name__ == "__main__":
    main()
