"""The training pipeline behind `stg-train` and `stg-eval`: a dataset in, OUT/model.stg and
OUT/metrics.json out.

    train(dataset, out, config, ...)                one run, or segment by segment for a long video
    train_segments(dataset, out, config, ...)       the segments of a plan (stg_train.segments), merged
    prepare_segments, finish_segments               its two ends, shared with stg_train.distributed
    model_frames(player, dataset, name)             the dataset frames a model covers (for stg-eval)
    run_demo(out, config, ...)                      the demo: synthetic scene, training, orbit video

A run trains (or resumes from OUT/checkpoint.pt), exports OUT/model.stg (checked against the runtime),
evaluates it with the runtime Player on the held-out camera at every frame and writes OUT/metrics.json.
Progress and notices go to stderr unless `quiet`.
"""
from __future__ import annotations

import json
import sys
import warnings
from dataclasses import asdict
from pathlib import Path
from typing import Sequence

import numpy as np

from stg_runtime.atomic import remove_leftovers, write_atomic
from stg_runtime.camera import orbit
from stg_runtime.player import Player
from stg_runtime.progress import progress_stages

from .config import DEMO_SCENE, DEMO_TRAINING  # noqa: F401 (re-exported: the benchmarks use them)
from .convert.merge import merge_files
from .data import DataError, load_dataset
from .export import export_trainer
from .metrics import evaluate_player, heldout, lpips_models
from .segments import (SegmentError, check_plan, finished, missing_message, plan_segments, pooled, segment_dir,
                       worst_check)
from .synthetic import SyntheticScene, write_n3v
from .trainer import Trainer, TrainConfig



def ensure_demo_scene(data, announce: bool = False, supersample: int = 1, seed: int = 0, layout: int = 0,
                      **sizes) -> Path:
    """The demo's synthetic scene, in the N3V layout, at `data`: written unless it is there already.
    sizes: any of DEMO_SCENE's cameras, frames, width, height to change; supersample: rays per pixel
    side (stg_train.synthetic.write_n3v; 1, the demo's, leaves the ground truth aliased where textures
    are finer than a pixel); seed, layout: SyntheticScene's (another scene: textures and object set);
    announce: say so on stderr before writing."""
    d = {**DEMO_SCENE, **sizes}
    data = Path(data)
    if not (data / "poses_bounds.npy").exists():
        if announce:
            print(f"writing the synthetic scene ({d['cameras']} cameras x {d['frames']} frames, "
                  f"{d['width']}x{d['height']}) to {data}", file=sys.stderr)
        scene = SyntheticScene(seed=seed, duration=d["frames"] / d["fps"], layout=layout)
        write_n3v(data, scene, num_cameras=d["cameras"],
                  num_frames=d["frames"], fps=d["fps"], width=d["width"], height=d["height"],
                  supersample=supersample)
    return data


def new_trainer(dataset, config: TrainConfig, out: Path, quiet: bool = False) -> Trainer:
    """Trainer(dataset, config, out) with progress bars while SfM computes the initial points and while
    the optical flow gives them their motion; its
    warnings (SfM found too few points) are printed as "stg-train: warning: ..." lines, and the initial
    points' split, coverage and depth bounds as "stg-train: ..." lines (unless quiet)."""
    with progress_stages(enabled=not quiet) as stage:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            trainer = Trainer(dataset, config, out_dir=out, init_progress=stage("structure from motion"),
                              motion_progress=stage("initial motion (optical flow)"))
    for w in caught:
        print(f"stg-train: warning: {w.message}", file=sys.stderr)
    if not quiet:
        for line in trainer.initial.describe().splitlines():
            print(f"stg-train: {line}", file=sys.stderr)
    return trainer


def _lpips(quiet: bool) -> dict:
    """lpips_models(), saying on stderr why LPIPS is left out when it is (unless quiet)."""
    models, why = lpips_models()
    if why and not quiet:
        print(f"stg-train: {why}", file=sys.stderr)
    return models


def _write_metrics(out: Path, metrics: dict) -> None:
    write_atomic(out / "metrics.json", json.dumps(metrics, indent=1) + "\n")


def train(dataset, out, config: TrainConfig, resume: bool = False, quiet: bool = False, check: bool = True,
          segment_frames: int | None = None, segments: Sequence[int] | None = None, lpips: dict | None = None,
          callback=None) -> dict:
    """Train (or resume) into `out`, export out/model.stg, evaluate it with the runtime and write
    out/metrics.json; returns the metrics. With segment_frames, a video of more frames (or any run
    naming `segments`, a list of indices) is trained segment by segment (train_segments). lpips: the
    LPIPS networks of the evaluation (default: metrics.lpips_models, when the lpips package works).
    callback(trainer) runs after every training step (Trainer.train's; the training viewer's).
    Raises DataError and SegmentError naming the problem."""
    if segment_frames and (segments is not None or len(plan_segments(dataset.num_frames, segment_frames)) > 1):
        return train_segments(dataset, out, config, segment_frames, segments, resume, quiet, check, callback)
    lpips = _lpips(quiet) if lpips is None else lpips
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    remove_leftovers(out)  # of a killed run: its checkpoint, model or metrics being written
    ckpt = out / "checkpoint.pt"
    if resume and ckpt.exists():
        trainer = Trainer.resume(dataset, ckpt, out_dir=out, device=config.device, splatter=config.splatter)
        if not quiet:
            print(f"resuming {ckpt} at step {trainer.step} of {trainer.config.iterations}", file=sys.stderr)
    else:
        if resume and not quiet:
            print(f"no checkpoint in {out}: starting a new run", file=sys.stderr)
        trainer = new_trainer(dataset, config, out, quiet)
    trainer.train(progress=not quiet, callback=callback)
    report = export_trainer(trainer, out / "model.stg", check=check)
    result = evaluate_player(Player(report.path, device="cpu"), dataset, lpips=lpips)
    metrics = {"heldout": heldout(result), "iterations": trainer.step, "train_seconds": trainer.seconds,
               "gaussians": trainer.params.count, "file_bytes": report.bytes,
               "export_check": None if report.diff is None else report.diff._asdict(),
               "settings": asdict(trainer.config)}
    if trainer.initial is not None:
        metrics["init"] = trainer.initial.summary()
    _write_metrics(out, metrics)
    return metrics


def train_segments(dataset, out, config: TrainConfig, segment_frames: int, indices: Sequence[int] | None = None,
                   resume: bool = False, quiet: bool = False, check: bool = True, callback=None) -> dict:
    """Train the segments `indices` (default: all) of `dataset` cut every segment_frames frames into
    OUT/segments/NN, then merge every segment into OUT/model.stg when all are finished, evaluate and
    write OUT/metrics.json; returns the metrics ("missing_segments" lists the indices still to train).

    resume: keep finished segments and continue an unfinished one from its checkpoint; otherwise the
    chosen segments are trained afresh. Raises SegmentError for indices outside the plan or an OUT
    cut differently, DataError for bad data (from the training runs).
    """
    out = Path(out)
    dataset, plan, todo = prepare_segments(dataset, out, segment_frames, indices, resume, quiet)
    lpips = _lpips(quiet)
    for i in todo:
        span, folder = plan[i], segment_dir(out, i, len(plan))
        if not quiet:
            print(f"segment {i} of 0-{len(plan) - 1} ({span.frames()}) -> {folder}", file=sys.stderr)
        train(dataset.frame_range(span.start, span.count), folder, config, resume, quiet, check, lpips=lpips,
              callback=callback)
    return finish_segments(dataset, out, config, segment_frames, quiet, lpips)


def prepare_segments(dataset, out: Path, segment_frames: int, indices: Sequence[int] | None, resume: bool,
                     quiet: bool = False):
    """The segments of a run before any is trained: (dataset with its frame cache cut at the segments,
    plan, indices to train). Checks the indices, OUT (creating it) and OUT's plan (SegmentError), removes leftovers of
    killed writes, and without `resume` the marks of finished segments of the chosen ones (so they
    are trained afresh); with it, says which finished segments are kept."""
    plan = plan_segments(dataset.num_frames, segment_frames)
    chosen = list(range(len(plan))) if indices is None else sorted(set(indices))
    bad = [i for i in chosen if not 0 <= i < len(plan)]
    if bad:
        raise SegmentError(f"--segments {','.join(map(str, bad))}: the {dataset.num_frames}-frame video has "
                           f"{len(plan)} segment{'s' if len(plan) > 1 else ''} of {segment_frames} frames "
                           f"(indices 0-{len(plan) - 1})")
    try:
        (out / "segments").mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise SegmentError(f"{out}: cannot create the output folder ({e.strerror or e})") from None
    check_plan(out, plan, segment_frames)
    remove_leftovers(out)
    remove_leftovers(out / "segments")
    todo = []
    for i in chosen:
        span, folder = plan[i], segment_dir(out, i, len(plan))
        if resume and finished(folder, span):
            if not quiet:
                print(f"segment {i} ({span.frames()}): finished, keeping {folder / 'model.stg'}", file=sys.stderr)
            continue
        if not resume:
            for name in ("metrics.json", "model.stg"):  # the marks of a finished segment
                (folder / name).unlink(missing_ok=True)
        todo.append(i)
    return dataset.chunked([(s.start, s.count) for s in plan]), plan, todo


def finish_segments(dataset, out: Path, config: TrainConfig, segment_frames: int, quiet: bool = False,
                    lpips: dict | None = None) -> dict:
    """After the segments' runs: merge every segment into OUT/model.stg when all are finished (else
    pool the finished ones' evaluations and say what is missing), evaluate, write OUT/metrics.json and
    return the metrics (see train_segments)."""
    lpips = _lpips(quiet) if lpips is None else lpips
    plan = plan_segments(dataset.num_frames, segment_frames)
    folders = [segment_dir(out, s.index, len(plan)) for s in plan]
    done = [s for s, f in zip(plan, folders) if finished(f, s)]
    missing = [s for s in plan if s not in done]
    per_segment, heldouts = [], []
    for s in done:
        m = json.loads((folders[s.index] / "metrics.json").read_text())
        heldouts.append(m["heldout"])
        per_segment.append({"index": s.index, "start_frame": s.start, "num_frames": s.count,
                            "folder": str(folders[s.index]), "iterations": m["iterations"],
                            "train_seconds": m["train_seconds"], "gaussians": m["gaussians"],
                            "file_bytes": m["file_bytes"], "heldout_psnr": m["heldout"]["psnr"],
                            "export_check": m["export_check"]})
    model_path = None
    if not missing:
        model_path = out / "model.stg"
        try:
            merge_files([folders[s.index] / "model.stg" for s in plan], model_path,
                        provenance={"tool": "stg-train", "segment_frames": segment_frames})
        except ValueError as e:
            raise SegmentError(f"cannot merge the segments of {out / 'segments'}: {e}") from None
        result = evaluate_player(Player(model_path, device="cpu"), dataset, lpips=lpips)
        file_bytes = model_path.stat().st_size
    else:  # the finished segments' own evaluations (of the same files, over their frames), pooled
        result = pooled(heldouts)
        file_bytes = sum(p["file_bytes"] for p in per_segment)
        print(missing_message(out, plan, missing, segment_frames, dataset.path), file=sys.stderr)
    metrics = {"heldout": heldout(result), "model": None if model_path is None else str(model_path),
               "segment_frames": segment_frames, "segments": per_segment,
               "missing_segments": [s.index for s in missing],
               "iterations": sum(p["iterations"] for p in per_segment),
               "train_seconds": sum(p["train_seconds"] for p in per_segment),
               "gaussians": sum(p["gaussians"] for p in per_segment), "file_bytes": file_bytes,
               "export_check": worst_check(per_segment), "settings": asdict(config.for_dataset(dataset))}
    _write_metrics(out, metrics)
    return metrics


def model_frames(player: Player, dataset, name) -> range:
    """The dataset frames that the model `player` plays covers (all of them, or a segment run's part).
    Raises DataError naming the model when it covers none of them or another frame rate."""
    first, end = player.model.start_frame, player.model.start_frame + player.num_frames
    if first >= dataset.num_frames or abs(player.fps - dataset.fps) > 1e-6:
        raise DataError(f"{name}: covers frames {first}-{end - 1} at {player.fps:g} fps, the dataset has "
                        f"{dataset.num_frames} at {dataset.fps:g} fps")
    return range(first, min(end, dataset.num_frames))


def run_demo(out, config: TrainConfig, resume: bool = False, quiet: bool = False, check: bool = True,
             segment_frames: int | None = None, segments: Sequence[int] | None = None, callback=None) -> dict:
    """The demo: the synthetic scene written into OUT/data (once), trained with `config`, and a
    novel-view video OUT/orbit.mp4 along an orbit around the training cameras; returns the metrics (no
    video while segments are missing)."""
    out = Path(out)
    data = ensure_demo_scene(out / "data", announce=not quiet)
    dataset = load_dataset(data, show_progress=not quiet, lazy=True)
    metrics = train(dataset, out, config, resume, quiet, check, segment_frames, segments, callback=callback)
    if metrics.get("missing_segments"):
        return metrics  # OUT/model.stg waits for the other segments (train_segments said which)
    player = Player(out / "model.stg", device="cpu")
    path = orbit([dataset.cameras[i] for i in dataset.train_cameras], dataset.num_frames)
    player.render_video(out / "orbit.mp4", path, times=np.arange(dataset.num_frames) / dataset.fps,
                        progress=not quiet)
    return metrics
