#!/usr/bin/env python
"""Realistic captures (issue 33): the same synthetic scene captured cleanly and as a real rig would
(per-camera exposure and white balance, vignetting, sensor noise, a small pose error:
stg_train.rig.capture.CaptureModel, what `stg-synth --realistic` writes), trained with and without the
per-camera appearance (TrainConfig.appearance) and pose refinement (TrainConfig.pose_refine), and scored
against the CLEAN lossless frames: raw and colour-aligned PSNR (stg_train.metrics, one affine colour map
per camera) on the held-out camera, rendered at its TRUE pose (scene.json), and on two novel views
inside the rig (ray traced); the same views again moved into the model's frame (capture.in_model_frame:
pictures fix a model only up to a similarity of the world, and the stated poses' frame is not the
truth's); and each of those again with its pose aligned to its own pictures against the trained model
(stg_train.rig.pose_align: test-time pose optimisation, as BARF and NeRF-- score pose-refining methods, the
clean capture's model the same way); plus the training cameras' pose error against the truth, as stated
and as refined.

    python bench/realistic.py [--iterations N] [--points N] [--seeds 0,1] [--variants plain,appearance,...]
                              [--captures clean,realistic] [--cameras C] [--frames F] [--width W]
                              [--height H] [--set KEY=VALUE ...] [--capture KEY=VALUE ...] [--threads 2]
                              [--data DIR] [--json PATH] [--checkpoints DIR [--reuse]]

Variants: default (TrainConfig's defaults: the falloff, the appearance and the pose refinement "auto",
decided from the rig's measurement, stg_train.rig.self_calibration.calibrate_rig), plain (none of the
three: the defaults before 2026-12-04), appearance, pose (pose_refine), both, colour (appearance
without its vignetting term), known (both, with the capture's true vignetting given as
TrainConfig.lens_falloff, as a flat-field calibration would give it), known-appearance (the same without pose refinement), measured
and measured-appearance (the same two with the vignetting measured from the cameras' overlap before
training, TrainConfig.lens_falloff "auto": stg_train.rig.self_calibration), lens-auto (that measurement
alone, no appearance or pose refinement). Each seed
is one realistic capture
(CaptureModel(seed=SEED), the knobs' defaults unless --capture changes them, e.g. --capture noise=0)
and the training seed; the scene is the demo's (12 cameras x 30 frames at 160x120 by default). Training
reads the lossless PNG frames of either capture. The defaults train with TrainConfig's defaults (3000
steps, 20000 initial points): about as long per run as `stg-train` on the demo scene.
"""
from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import stg_train  # noqa: F401  (first: it configures OpenMP before torch loads)
import numpy as np
import torch

from stg_train.rig.capture import CaptureModel, capture_record, in_model_frame, pose_errors
from stg_train.data import load_n3v
from stg_train.data.bounds import typical_depth
from stg_train.data.dataset import Dataset
from stg_train.metrics import evaluate_images
from stg_train.rig.pose_align import align_view
from stg_train.pipeline import DEMO_SCENE
from stg_train.synthetic import NOVEL_VIEWS, SyntheticScene, novel_view_dataset, write_n3v
from stg_train.trainer import Trainer, TrainConfig

#: Every variant but "default" starts from no falloff, no appearance and no pose refinement (the
#: defaults before "auto", 2026-12-04).
_OFF = {"appearance": False, "lens_falloff": None, "pose_refine": False}
VARIANTS = {"default": {}, "plain": _OFF, "appearance": {**_OFF, "appearance": True},
            "pose": {**_OFF, "pose_refine": True},
            "both": {**_OFF, "appearance": True, "pose_refine": True},
            "colour": {**_OFF, "appearance": True, "appearance_vignetting": False},
            "known": {"appearance": True, "pose_refine": True, "lens_falloff": "capture"},
            "known-appearance": {"appearance": True, "pose_refine": False, "lens_falloff": "capture"},
            "measured": {"appearance": True, "pose_refine": True, "lens_falloff": "auto"},
            "lens-auto": {**_OFF, "lens_falloff": "auto"},
            "measured-appearance": {"appearance": True, "pose_refine": False, "lens_falloff": "auto"}}


def parse_setting(text: str) -> tuple[str, object]:
    """KEY=VALUE, VALUE as JSON when it parses, else the string."""
    key, sep, value = text.partition("=")
    if not sep or not key:
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE, got {text!r}")
    try:
        return key, json.loads(value)
    except json.JSONDecodeError:
        return key, value


def write_captures(root: Path, size: dict, capture: CaptureModel) -> tuple[Path, Path, SyntheticScene]:
    """(clean folder, realistic folder, scene): the demo scene written cleanly and through `capture`
    (each once: kept when there; the realistic folder is named by the seed and by the knobs changed from
    their defaults)."""
    scene = SyntheticScene(seed=0, duration=size["frames"] / size["fps"])
    common = dict(num_cameras=size["cameras"], num_frames=size["frames"], fps=size["fps"], width=size["width"],
                  height=size["height"])
    changed = {k: v for k, v in capture.settings().items() if k != "seed" and v != getattr(CaptureModel(), k)}
    tag = "".join(f"-{k}{v:g}" for k, v in sorted(changed.items()))
    clean, real = root / "clean", root / f"realistic-{capture.seed}{tag}"
    if not (clean / "scene.json").exists():
        write_n3v(clean, scene, **common)
    if not (real / "scene.json").exists():
        write_n3v(real, scene, capture=capture, **common)
    return clean, real, scene


def heldout_truth(clean: Dataset, record: dict | None) -> Dataset:
    """The held-out camera at its true pose (the capture record's, else the clean dataset's) with the
    clean lossless frames."""
    ci = clean.test_cameras[0]
    cam = clean.cameras[ci]
    if record is not None:
        true = {c["name"]: c["true_world_to_camera"] for c in record["cameras"]}
        cam = replace(cam, world_to_camera=np.asarray(true[cam.name]))
    frames = np.stack([clean.frame(ci, j) for j in range(clean.num_frames)])[None]
    return Dataset([cam], frames, clean.fps, test_cameras=[0])


def in_frame(views: dict[str, Dataset], trainer: Trainer, data: Dataset, record: dict | None) -> dict[str, Dataset]:
    """`views` (posed in the true world) moved into the trained model's frame (capture.in_model_frame):
    its training cameras as it holds them (stated, or refined) against their truth (the capture record's;
    a clean capture's stated poses are the truth), in their pictures at the scene's depth
    (data.bounds.typical_depth)."""
    truth = {c.name: np.asarray(c.world_to_camera) for c in data.cameras} if record is None else \
        {c["name"]: np.asarray(c["true_world_to_camera"]) for c in record["cameras"]}
    held = trainer.refined_cameras()
    model = np.stack([held[i].world_to_camera for i in data.train_cameras])
    true = np.stack([truth[data.cameras[i].name] for i in data.train_cameras])
    depth = typical_depth(data.bounds[data.train_cameras])
    return {name: Dataset(in_model_frame(ds.cameras, model, true, depth), ds.frames, ds.fps, test_cameras=ds.test_cameras)
            for name, ds in views.items()}


def pose_aligned(views: dict[str, Dataset], trainer: Trainer, depth: float) -> tuple[dict[str, Dataset], dict]:
    """(`views` each with its pose aligned to its own pictures against the trained model's canonical
    renders (pose_align.align_view, as `stg-eval --align-poses`: 4 frames, an affine colour map),
    {view: (degrees, world units) moved})."""
    out, moved = {}, {}
    for name, ds in views.items():
        result = align_view(lambda camera, j: trainer.render_numpy(camera, j / ds.num_frames), ds.cameras[0],
                            lambda j: ds.image(0, j), range(ds.num_frames), depth)
        out[name] = Dataset([result.camera], ds.frames, ds.fps, test_cameras=[0])
        moved[name] = (result.rotation_deg, result.shift)
    return out, moved


def score(trainer: Trainer, views: dict[str, Dataset]) -> dict:
    """{view: (psnr, aligned_psnr)} of the trainer's canonical renders (no appearance) against `views`."""
    out = {}
    for name, ds in views.items():
        r = evaluate_images(lambda ci, j: trainer.render_numpy(ds.cameras[ci], j / ds.num_frames), ds)
        out[name] = (r["psnr"], r["aligned_psnr"])
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    d = TrainConfig()
    ap.add_argument("--iterations", type=int, default=d.iterations)
    ap.add_argument("--points", type=int, default=d.num_points)
    ap.add_argument("--seeds", default="0", help="comma-separated capture and training seeds (default 0)")
    ap.add_argument("--variants", default="plain,default", help="comma-separated subset of: " + ", ".join(VARIANTS))
    ap.add_argument("--captures", default="clean,realistic", help="comma-separated subset of: clean, realistic")
    ap.add_argument("--cameras", type=int, default=DEMO_SCENE["cameras"])
    ap.add_argument("--frames", type=int, default=DEMO_SCENE["frames"])
    ap.add_argument("--width", type=int, default=DEMO_SCENE["width"])
    ap.add_argument("--height", type=int, default=DEMO_SCENE["height"])
    ap.add_argument("--set", type=parse_setting, action="append", default=[], metavar="KEY=VALUE",
                    help="a TrainConfig field for every run (VALUE is JSON, else a string)")
    ap.add_argument("--capture", type=parse_setting, action="append", default=[], metavar="KEY=VALUE",
                    help="a CaptureModel field (e.g. noise=0, rotation_deg=0.5)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--data", default=None, help="folder for the captures (written once; default: a temp folder)")
    ap.add_argument("--json", default=None, help="also write the results as JSON here")
    ap.add_argument("--checkpoints", default=None, help="also save each trained model's checkpoint in this folder")
    ap.add_argument("--reuse", action="store_true",
                    help="score the model saved in --checkpoints instead of training it again, where there is one")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    os.environ.setdefault("NUMBA_NUM_THREADS", str(args.threads))
    size = dict(cameras=args.cameras, frames=args.frames, width=args.width, height=args.height, fps=DEMO_SCENE["fps"])
    root = Path(args.data or tempfile.mkdtemp(prefix="stg_realistic_"))
    settings = dict(args.set)
    results = []
    for seed in [int(s) for s in args.seeds.split(",")]:
        capture = CaptureModel(**{**dict(args.capture), "seed": seed})
        clean_dir, real_dir, scene = write_captures(root, size, capture)
        clean = load_n3v(clean_dir, prefer_png=True)
        record = capture_record(real_dir)
        novel = novel_view_dataset(scene, size["frames"], size["fps"], size["width"], size["height"],
                                   positions=NOVEL_VIEWS[:2])
        views = {"held-out": heldout_truth(clean, record),
                 **{f"novel {k + 1}": Dataset([novel.cameras[k]], novel.frames[k:k + 1], novel.fps, test_cameras=[0])
                    for k in range(2)}}
        for capture_name in args.captures.split(","):
            data = load_n3v(clean_dir if capture_name == "clean" else real_dir, prefer_png=True)
            names = [data.cameras[i].name for i in data.train_cameras]
            for variant in args.variants.split(","):
                chosen = {**settings, **VARIANTS[variant]}
                if chosen.get("lens_falloff") == "capture":  # the capture's own vignetting, as calibrated
                    vignetting = capture.vignetting if capture_name == "realistic" else 0.0
                    chosen["lens_falloff"] = (-vignetting, 0.0) if vignetting else None
                config = TrainConfig(iterations=args.iterations, num_points=args.points, seed=seed, **chosen)
                start = time.perf_counter()
                saved = None if not args.checkpoints else Path(args.checkpoints) / f"{seed}-{capture_name}-{variant}.pt"
                if args.reuse and saved is not None and saved.exists():
                    trainer = Trainer.resume(data, saved)
                else:
                    trainer = Trainer(data, config)
                    trainer.train(progress=False)
                    if saved is not None:
                        saved.parent.mkdir(parents=True, exist_ok=True)
                        trainer.save_checkpoint(saved)
                seconds = time.perf_counter() - start
                framed = in_frame(views, trainer, data, record if capture_name == "realistic" else None)
                aligned, moved = pose_aligned(framed, trainer, typical_depth(data.bounds[data.train_cameras]))
                row = {"seed": seed, "capture": capture_name, "variant": variant, "seconds": seconds,
                       "gaussians": trainer.params.count, "views": score(trainer, views),
                       "views_in_frame": score(trainer, framed), "views_aligned": score(trainer, aligned),
                       "alignment": moved}
                if trainer.rig.calibration is not None and trainer.rig.calibration.estimate is not None:
                    row["measured_falloff"] = list(trainer.rig.calibration.estimate.k)
                    row["chosen"] = {k: getattr(trainer.config, k) for k in ("lens_falloff", "appearance", "pose_refine")}
                if trainer.rig.remeasure_note:
                    row["remeasured"] = trainer.rig.remeasure_note
                if trainer.rig.appearance is not None:
                    summary = trainer.rig.appearance.summary()
                    row["vignetting"] = np.mean([a["vignetting"] for a in summary], axis=0).tolist()
                    row["matrix_spread"] = float(np.std([np.diag(a["matrix"]) for a in summary]))
                if trainer.rig.poses is not None:
                    state = trainer.rig.poses.state_dict()
                    row["correction"] = (float(np.degrees(state["rotation"].norm(dim=1).mean())),
                                         float(state["translation"].norm(dim=1).mean() * state["scale"]))
                if capture_name == "realistic":
                    for key, cams in (("pose_stated", data.cameras), ("pose_refined", trainer.refined_cameras())):
                        e = pose_errors(cams, record, names, typical_depth(data.bounds[data.train_cameras]))
                        row[key] = (e["rotation_deg"], e["translation"], e.get("aligned_rotation_deg"),
                                    e.get("aligned_translation"))
                results.append(row)
                figures = "  ".join(f"{v}: {p:.2f} / {a:.2f} dB" for v, (p, a) in row["views"].items())
                pose = "" if "pose_refined" not in row else (
                    f"  pose error {row['pose_stated'][0]:.3f} deg {row['pose_stated'][1]:.4f} -> "
                    f"{row['pose_refined'][0]:.3f} deg {row['pose_refined'][1]:.4f} (gauge removed: "
                    f"{row['pose_stated'][2]:.3f} deg {row['pose_stated'][3]:.4f} -> "
                    f"{row['pose_refined'][2]:.3f} deg {row['pose_refined'][3]:.4f})")
                extra = "".join(f"  {k} {np.round(row[k], 4).tolist()}" for k in ("vignetting", "measured_falloff", "correction")
                                if k in row)
                if "chosen" in row:
                    k = row["chosen"]["lens_falloff"]
                    extra += (f"  chosen: falloff {None if k is None else np.round(k, 3).tolist()}, "
                              f"appearance {row['chosen']['appearance']}, pose refinement {row['chosen']['pose_refine']}")
                print(f"seed {seed} {capture_name:9s} {variant:10s} {figures}{pose}{extra}  ({row['gaussians']} Gaussians, "
                      f"{row['seconds']:.0f} s)", flush=True)
                figures = "  ".join(f"{v}: {p:.2f} / {a:.2f} dB" for v, (p, a) in row["views_in_frame"].items())
                if "remeasured" in row:
                    print(f"{'':31s}{row['remeasured']}", flush=True)
                print(f"{'':31s}in the model's frame: {figures}", flush=True)
                figures = "  ".join(f"{v}: {p:.2f} / {a:.2f} dB (moved {row['alignment'][v][0]:.3f} deg, "
                                    f"{row['alignment'][v][1]:.4f})" for v, (p, a) in row["views_aligned"].items())
                print(f"{'':31s}each view's pose aligned: {figures}", flush=True)
    print("\nraw / colour-aligned PSNR against the clean lossless frames (held-out camera at its true pose; in the "
          "model's frame: every view moved by the similarity of the world that best takes the true training poses "
          "to the model's; each view's pose aligned: then aligned to its own pictures, stg_train.rig.pose_align)")
    if args.json:
        Path(args.json).write_text(json.dumps({"settings": {**vars(args), "set": settings}, "results": results},
                                              indent=1, default=str) + "\n")


if __name__ == "__main__":
    main()
