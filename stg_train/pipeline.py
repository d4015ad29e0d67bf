"""The training pipeline behind `stg-train` and `stg-eval`: a dataset in, OUT/model.stg and
OUT/metrics.json out.

    train(dataset, out, config, ...)                one run, or segment by segment for a long video
    train_segments(dataset, out, config, ...)       the segments of a plan (stg_train.segments), merged
    prepare_segments, finish_segments               its two ends, shared with stg_train.distributed
    model_frames(player, dataset, name)             the dataset frames a model covers (for stg-eval)
    check_cameras(player, dataset, name)            whether a model was trained on the dataset's cameras
    run_demo(out, config, ...)                      the demo: synthetic scene, training, orbit video
    claim_output(out, dataset, ...)                 refuse to start a new run over an old one (or clear it)
    Interrupted, RunExists, ResumeConflict          a run stopped by Ctrl-C; a used OUT; a setting --resume cannot change

A run trains (or resumes from OUT/checkpoint.pt), exports OUT/model.stg (checked against the runtime),
evaluates it with the runtime Player on the held-out camera at every frame and writes OUT/metrics.json.
Progress and notices go to stderr unless `quiet`.

With stop_on_signal, Ctrl-C (SIGINT) or SIGTERM during training stops the run after the current step:
the checkpoint is saved and Interrupted raised (a second Ctrl-C stops at once). On resume, the settings
in RESUMABLE may change (`given` names those the user set); any other setting that differs from the
checkpoint's is refused (ResumeConflict).
"""
from __future__ import annotations

import json
import signal
import sys
import threading
import warnings
from contextlib import contextmanager
from dataclasses import asdict
from pathlib import Path
from typing import Sequence

import numpy as np

from stg_runtime.atomic import remove_leftovers, write_atomic
from stg_runtime.camera import orbit
from stg_runtime.player import Player
from stg_runtime.progress import progress_stages

from .checkpoint import CheckpointError, read_checkpoint
from .config import DEMO_SCENE, DEMO_TRAINING  # noqa: F401 (re-exported: the benchmarks use them)
from .convert.merge import merge_files
from .data import DataError, load_dataset
from .export import export_trainer
from .metrics import evaluate_player, heldout, lpips_models
from .rig.self_calibration import AUTO_FIELDS, calibrate_rig, needs_calibration
from .segments import (PLAN_NAME, SegmentError, cache_chunks, check_plan, finished, missing_message, plan_segments, pooled,
                       segment_dir, segment_view, worst_check)
from .synthetic import SyntheticScene, write_n3v
from .trainer import Trainer, TrainConfig, run_steps
from .warm import chain_head, start_of, warm_steps



def ensure_demo_scene(data, announce: bool = False, supersample: int = 1, seed: int = 0, layout: int = 0,
                      duration: float | None = None, start: float = 0.0, **sizes) -> Path:
    """The demo's synthetic scene, in the N3V layout, at `data`: written unless it is there already.
    sizes: any of DEMO_SCENE's cameras, frames, width, height to change; supersample: rays per pixel
    side (stg_train.synthetic.write_n3v; 1, the demo's, leaves the ground truth aliased where textures
    are finer than a pixel); seed, layout: SyntheticScene's (another scene: textures and object set);
    duration: SyntheticScene's, the seconds over which the fader appears and vanishes (default: the
    clip's, frames / fps); start: SyntheticScene's, the scene's time at the first frame, seconds (a clip
    that begins later in the scene, or before it); announce: say so on stderr before writing."""
    d = {**DEMO_SCENE, **sizes}
    data = Path(data)
    if not (data / "poses_bounds.npy").exists():
        if announce:
            print(f"writing the synthetic scene ({d['cameras']} cameras x {d['frames']} frames, "
                  f"{d['width']}x{d['height']}) to {data}", file=sys.stderr)
        duration = d["frames"] / d["fps"] if duration is None else duration
        scene = SyntheticScene(seed=seed, duration=duration, layout=layout, start=start)
        write_n3v(data, scene, num_cameras=d["cameras"],
                  num_frames=d["frames"], fps=d["fps"], width=d["width"], height=d["height"],
                  supersample=supersample)
    return data


@contextmanager
def warnings_said():
    """Warnings raised inside the block, printed as "stg-train: warning: ..." lines on stderr once it
    ends (after any progress bar opened inside it has closed)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        yield
    for w in caught:
        print(f"stg-train: warning: {w.message}", file=sys.stderr)


#: The progress bar's title while the rig is measured (stg_train.rig.self_calibration).
CALIBRATION_STAGE = "measuring the rig (lenses, colours, poses)"


def new_trainer(dataset, config: TrainConfig, out: Path, quiet: bool = False, warm=None) -> Trainer:
    """Trainer(dataset, config, out) with progress bars while the rig is measured (a setting "auto",
    stg_train.rig.self_calibration), while SfM computes the initial points and while the optical flow gives
    them their motion; its warnings (SfM found too few points) are printed as "stg-train: warning: ..."
    lines, and what the rig's measurement decided and the initial points' split, coverage and depth
    bounds as "stg-train: ..." lines (unless quiet). warm: a stg_train.warm.WarmStart to start from
    instead of initial points (a warm-started segment)."""
    with warnings_said(), progress_stages(enabled=not quiet) as stage:
        trainer = Trainer(dataset, config, out_dir=out, init_progress=stage("structure from motion"),
                          motion_progress=stage("initial motion (optical flow)"),
                          calibration_progress=stage(CALIBRATION_STAGE), warm=warm)
    if not quiet:
        for line in (() if trainer.rig.calibration is None else trainer.rig.calibration.notes):
            print(f"stg-train: {line}", file=sys.stderr)
        if warm is not None:
            print(f"stg-train: warm start: {warm.carried} Gaussians carried from the previous segment, "
                  f"{warm.dropped} past ones dropped; {trainer.steps} steps", file=sys.stderr)
        for line in (() if trainer.initial is None else trainer.initial.describe().splitlines()):
            print(f"stg-train: {line}", file=sys.stderr)
    return trainer


def calibrated_once(dataset, config: TrainConfig, given: dict[str, str] | None = None,
                    quiet: bool = False) -> tuple[TrainConfig, dict[str, str]]:
    """For a video trained in segments: (config, given) with its "auto" settings (AUTO_FIELDS) decided
    once from the whole video's frames (stg_train.rig.self_calibration.calibrate_rig; said on stderr unless
    quiet), so that every segment trains with the same choices; `given` loses the options so decided (a
    resumed segment keeps its checkpoint's choices). Unchanged when nothing is "auto"."""
    if not needs_calibration(config):
        return config, dict(given or {})
    with progress_stages(enabled=not quiet) as stage:
        decided, calibration = calibrate_rig(dataset, config, progress=stage(CALIBRATION_STAGE))
    if not quiet:
        for line in calibration.notes:
            print(f"stg-train: {line}", file=sys.stderr)
    auto = {name for name in AUTO_FIELDS if getattr(config, name) == "auto"}
    return decided, {k: v for k, v in (given or {}).items() if k not in auto}


def _lpips(quiet: bool) -> dict:
    """lpips_models(), saying on stderr why LPIPS is left out when it is (unless quiet)."""
    models, why = lpips_models()
    if why and not quiet:
        print(f"stg-train: {why}", file=sys.stderr)
    return models


def _write_metrics(out: Path, metrics: dict) -> None:
    write_atomic(out / "metrics.json", json.dumps(metrics, indent=1) + "\n")


#: TrainConfig fields that a resumed run may change (the checkpoint's value is replaced, and the run
#: says so); a resumed run keeps every other setting of its checkpoint.
RESUMABLE = ("iterations", "checkpoint_every", "device", "splatter")
#: What a run leaves in its folder: the files whose presence means OUT holds a run.
RUN_FILES = ("checkpoint.pt", "model.stg", "metrics.json")


class RunExists(DataError):
    """OUT already holds a run (finished or partial) and neither resume nor force was asked for."""


class ResumeConflict(DataError):
    """A setting given with resume differs from the checkpoint's and cannot change mid-run, or the
    checkpoint is one this version cannot continue."""


class Interrupted(Exception):
    """Training stopped by Ctrl-C (SIGINT) or SIGTERM after the checkpoint was saved: checkpoint (its
    path), step, iterations."""

    def __init__(self, checkpoint: Path, step: int, iterations: int):
        super().__init__(f"interrupted at step {step} of {iterations}; saved {checkpoint}")
        self.checkpoint, self.step, self.iterations = Path(checkpoint), step, iterations


class _Stop(Exception):
    """Raised from the step callback when a stop was requested."""


def _describe_run(folder: Path) -> str | None:
    """'a finished run (...)' / 'an unfinished run (...)' for a folder holding RUN_FILES; None if none."""
    present = [n for n in RUN_FILES if (folder / n).exists()]
    if not present:
        return None
    state = "a finished run" if "metrics.json" in present and "model.stg" in present else "an unfinished run"
    try:
        steps = json.loads((folder / "metrics.json").read_text()).get("iterations")
    except (OSError, ValueError, AttributeError):
        steps = None
    return f"{state} ({', '.join(present)}{f', {steps} steps' if steps else ''})"


def _check_trainable(dataset) -> None:
    """DataError when the dataset leaves no camera to train on."""
    if len(dataset.train_cameras) == 0:
        raise DataError(f"{dataset.path}: {len(dataset.cameras)} camera(s), all held out for testing: training needs "
                        "at least one more camera")


def claim_output(out, dataset=None, segment_frames: int | None = None, segments: Sequence[int] | None = None,
                 resume: bool = False, force: bool = False) -> None:
    """Check OUT before a run starts. RunExists naming the choices when OUT (or, for a segment run, one
    of the chosen segments' folders) holds a run and neither `resume` nor `force` is set; with `force`
    the old run's files there are removed (a new run starts from scratch). DataError when OUT is a file.
    dataset, segment_frames, segments: as for train (they decide which folders a run writes; a dataset
    without a camera to train on is refused here too)."""
    out = Path(out)
    if dataset is not None:
        _check_trainable(dataset)
    if out.exists() and not out.is_dir():
        raise DataError(f"--out {out}: is a file, not a folder")
    for parent in out.parents:
        if parent.exists():
            if not parent.is_dir():
                raise DataError(f"--out {out}: cannot create it: {parent} is a file")
            break
    folders = [out]
    if dataset is not None and segment_frames and (
            segments is not None or len(plan_segments(dataset.num_frames, segment_frames)) > 1):
        # a segment run: its segments' folders (OUT's own files are the merge of whatever is finished)
        plan = plan_segments(dataset.num_frames, segment_frames)
        chosen = range(len(plan)) if segments is None else sorted(set(segments))
        _check_indices(chosen, plan, dataset.num_frames, segment_frames)
        if (out / "segments" / PLAN_NAME).exists():
            check_plan(out, plan, segment_frames)  # OUT cut differently: refused before anything else
        folders = [segment_dir(out, i, len(plan)) for i in chosen]
    if resume:
        return
    used = [(f, d) for f in folders if (d := _describe_run(f))]
    if not used:
        return
    if not force:
        folder, what = used[0]
        raise RunExists(f"{folder} holds {what}: continue it with --resume, write to a new --out, or add --force "
                        "to train again from scratch (replacing it)")
    for folder, _ in used:
        for name in (*RUN_FILES, "orbit.mp4", REFINED_CAMERAS):
            (folder / name).unlink(missing_ok=True)


@contextmanager
def _stop_requests(enabled: bool):
    """Yields stop_requested(): with `enabled` (and on the main thread), Ctrl-C and SIGTERM only set a
    flag, read after each training step; a second Ctrl-C raises KeyboardInterrupt at once."""
    if not enabled or threading.current_thread() is not threading.main_thread():
        yield lambda: False
        return
    requested = []

    def handler(signum, frame):
        if requested:
            raise KeyboardInterrupt
        requested.append(signum)

    old = {sig: signal.signal(sig, handler) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield lambda: bool(requested)
    finally:
        for sig, h in old.items():
            signal.signal(sig, h)


def _run_training(trainer: Trainer, ckpt: Path, quiet: bool, callback, stop_on_signal: bool,
                  label: str = "train", job: tuple[int, int] | None = None) -> None:
    """trainer.train (label, job: its progress bar's), stoppable by Ctrl-C / SIGTERM after a step
    (stop_on_signal): then the checkpoint is saved and Interrupted raised."""
    with _stop_requests(stop_on_signal) as stop_requested:
        def step_done(t):
            if callback is not None:
                callback(t)
            if stop_requested():
                raise _Stop
        try:
            trainer.train(progress=not quiet, callback=step_done, label=label, job=job)
        except _Stop:
            trainer.save_checkpoint(ckpt)
            raise Interrupted(ckpt, trainer.step, trainer.steps) from None


def _resume(dataset, ckpt: Path, out: Path, config: TrainConfig, given: dict[str, str], quiet: bool) -> Trainer:
    """Trainer.resume with the RESUMABLE settings the user gave applied (said on stderr); ResumeConflict
    for another given setting that differs from the checkpoint's."""
    try:
        saved = TrainConfig.from_dict(read_checkpoint(ckpt)["config"])
    except CheckpointError as e:
        raise ResumeConflict(f"{e}: start afresh with --force or a new --out") from None
    changes, notes = {}, []
    for name, option in sorted(given.items()):
        new, old = getattr(config, name), getattr(saved, name)
        if name in ("device", "splatter") or new == old:
            continue
        if name in AUTO_FIELDS and new == "auto":  # the checkpoint holds what its run measured
            continue
        if name not in RESUMABLE:
            raise ResumeConflict(f"{option}: {ckpt} was trained with {name} = {old!r}, which a resumed run keeps: "
                                 f"leave {option.split()[0]} out, or start afresh with --force or a new --out")
        changes[name] = new
        notes.append(f"{option} replaces the checkpoint's {old!r}")
    try:
        trainer = Trainer.resume(dataset, ckpt, out_dir=out, device=config.device, splatter=config.splatter,
                                 changes=changes)
    except ValueError as e:  # a checkpoint this version cannot continue (Trainer.resume says why)
        raise ResumeConflict(str(e)) from None
    if trainer.step > trainer.steps:
        raise ResumeConflict(f"{given.get('iterations', '--iterations')}: {ckpt} is already at step {trainer.step}: "
                             f"give more iterations than {trainer.step}")
    if not quiet:
        said = f" ({'; '.join(notes)})" if notes else ""
        if trainer.step >= trainer.steps:
            print(f"{ckpt} is finished (step {trainer.step} of {trainer.steps}){said}: exporting and "
                  f"evaluating it again; --iterations N (more than {trainer.step}) trains on", file=sys.stderr)
        else:
            print(f"resuming {ckpt} at step {trainer.step} of {trainer.steps}{said}", file=sys.stderr)
    return trainer


def train(dataset, out, config: TrainConfig, resume: bool = False, quiet: bool = False, check: bool = True,
          segment_frames: int | None = None, segments: Sequence[int] | None = None, lpips: dict | None = None,
          callback=None, given: dict[str, str] | None = None, stop_on_signal: bool = False, warm=None,
          label: str = "train", job: tuple[int, int] | None = None) -> dict:
    """Train (or resume) into `out`, export out/model.stg, evaluate it with the runtime and write
    out/metrics.json; returns the metrics. With segment_frames, a video of more frames (or any run
    naming `segments`, a list of indices) is trained segment by segment (train_segments). lpips: the
    LPIPS networks of the evaluation (default: metrics.lpips_models, when the lpips package works).
    callback(trainer) runs after every training step (Trainer.train's; the training viewer's).
    given: TrainConfig field -> the option that set it (e.g. {"iterations": "--iterations 500"}): on
    resume, these replace the checkpoint's where RESUMABLE and are refused where not (ResumeConflict).
    stop_on_signal: Ctrl-C / SIGTERM save the checkpoint and raise Interrupted (see the module doc).
    warm: a stg_train.warm.WarmStart a new run starts from (a resumed run continues its checkpoint);
    label, job: the progress bar's title and the whole job's steps (Trainer.train).
    Raises DataError and SegmentError naming the problem."""
    _check_trainable(dataset)
    if segment_frames and (segments is not None or len(plan_segments(dataset.num_frames, segment_frames)) > 1):
        return train_segments(dataset, out, config, segment_frames, segments, resume, quiet, check, callback,
                              given, stop_on_signal)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    remove_leftovers(out)  # of a killed run: its checkpoint, model or metrics being written
    ckpt = out / "checkpoint.pt"
    if resume and ckpt.exists():
        trainer = _resume(dataset, ckpt, out, config, given or {}, quiet)
    else:
        if resume and not quiet:
            print(f"no checkpoint in {out}: starting a new run", file=sys.stderr)
        trainer = new_trainer(dataset, config, out, quiet, warm)
    lpips = _lpips(quiet) if lpips is None else lpips  # (said after the run's own settings and notices)
    if trainer.step < trainer.steps:
        _run_training(trainer, ckpt, quiet, callback, stop_on_signal, label, job)
    if trainer.rig.remeasure_note and not quiet:
        print(f"stg-train: {trainer.rig.remeasure_note}", file=sys.stderr)
    with warnings_said():  # export's ExportWarning: said, the run goes on
        report = export_trainer(trainer, out / "model.stg", check=check)
    result = evaluate_player(Player(report.path, device="cpu"), dataset.shown(), lpips=lpips)
    metrics = {"heldout": heldout(result), "iterations": trainer.step, "train_seconds": trainer.seconds,
               "warm": trainer.warm,
               "gaussians": trainer.params.count, "file_bytes": report.bytes,
               "export_check": None if report.diff is None else report.diff._asdict(),
               "settings": asdict(trainer.config)}
    if trainer.initial is not None:
        metrics["init"] = trainer.initial.summary()
    metrics.update(_refined_cameras(trainer, out, quiet))
    _write_metrics(out, metrics)
    return metrics


#: Where a run with pose refinement writes its refined cameras (stg_runtime.camera's camera-path JSON).
REFINED_CAMERAS = "refined_cameras.json"


def _refined_cameras(trainer: Trainer, out: Path, quiet: bool) -> dict:
    """With pose refinement: write OUT/refined_cameras.json and, when the dataset's scene.json records the
    capture's true poses (stg_train.rig.capture), say how far the training cameras were and are from them;
    returns {"pose_error": {"stated": ..., "refined": ...}} for metrics.json (or {})."""
    if trainer.rig.poses is None:
        return {}
    from stg_runtime.camera import save_camera_path

    from .rig.capture import capture_record, pose_errors

    cameras = trainer.refined_cameras()
    save_camera_path(out / REFINED_CAMERAS, cameras)
    ds = trainer.dataset
    record = None if ds.path is None else capture_record(ds.path)
    if record is None:
        return {}
    names = [ds.cameras[i].name for i in ds.train_cameras]
    depth = trainer.rig.poses.depth  # the scene's depth at which pose refinement measures the gauge
    stated, refined = pose_errors(ds.cameras, record, names, depth), pose_errors(cameras, record, names, depth)
    if not quiet:
        aligned = "" if "aligned_rotation_deg" not in stated else (
            f"; with the rig's common similarity removed, rotation {stated['aligned_rotation_deg']:.3f} -> "
            f"{refined['aligned_rotation_deg']:.3f} degrees, position {stated['aligned_translation']:.4g} -> "
            f"{refined['aligned_translation']:.4g}")
        print(f"stg-train: pose error of the training cameras against {ds.path}/scene.json's truth: rotation "
              f"{stated['rotation_deg']:.3f} -> {refined['rotation_deg']:.3f} degrees, position {stated['translation']:.4g} "
              f"-> {refined['translation']:.4g} (means; stated -> refined){aligned}", file=sys.stderr)
    keep = ("rotation_deg", "translation", "max_rotation_deg", "max_translation", "aligned_rotation_deg",
            "aligned_translation")
    return {"pose_error": {"stated": {k: stated[k] for k in keep if k in stated},
                           "refined": {k: refined[k] for k in keep if k in refined}}}


def train_segments(dataset, out, config: TrainConfig, segment_frames: int, indices: Sequence[int] | None = None,
                   resume: bool = False, quiet: bool = False, check: bool = True, callback=None,
                   given: dict[str, str] | None = None, stop_on_signal: bool = False) -> dict:
    """Train the segments `indices` (default: all) of `dataset` cut every segment_frames frames into
    OUT/segments/NN, then merge every segment into OUT/model.stg when all are finished, evaluate and
    write OUT/metrics.json; returns the metrics ("missing_segments" lists the indices still to train).

    resume: keep finished segments and continue an unfinished one from its checkpoint; otherwise the
    chosen segments are trained afresh. Raises SegmentError for indices outside the plan or an OUT
    cut differently, DataError for bad data (from the training runs).
    """
    out = Path(out)
    dataset, plan, todo = prepare_segments(dataset, out, segment_frames, indices, resume, quiet,
                                                   config.segment_context)
    if todo:
        config, given = calibrated_once(dataset, config, given, quiet)
    lpips = _lpips(quiet)
    steps = {i: segment_steps(dataset, plan, i, config) for i in todo}
    done = 0
    for i in todo:
        span, folder = plan[i], segment_dir(out, i, len(plan))
        warm = None if (resume and (folder / "checkpoint.pt").exists()) else start_of(out, plan, i, config, config.device)
        if not quiet:
            how = "" if config.segment_schedule != "warm" else (
                f", warm from segment {i - 1}" if warm is not None else ", cold")
            print(f"segment {i} of 0-{len(plan) - 1} ({span.frames()}{how}) -> {folder}", file=sys.stderr)
        train(segment_view(dataset, span, config.segment_context), folder, config, resume, quiet, check, lpips=lpips,
              callback=callback, given=given, stop_on_signal=stop_on_signal, warm=warm,
              label=f"segment {i}/{len(plan) - 1}", job=(done, sum(steps.values())))
        done += steps[i]
    return finish_segments(dataset, out, config, segment_frames, quiet, lpips)


def segment_steps(dataset, plan, index: int, config: TrainConfig) -> int:
    """The training steps segment `index` of `plan` is expected to take (trainer.run_steps of its view;
    a warm segment's share, warm.warm_steps, unless it heads a chain), for the job's progress bar."""
    view = segment_view(dataset, plan[index], config.segment_context)
    cold = config.segment_schedule != "warm" or chain_head(index, config.warm_chain)
    return run_steps(config.iterations if cold else warm_steps(config.iterations, config.warm_fraction), view)


def _check_indices(chosen, plan, num_frames: int, segment_frames: int) -> None:
    """SegmentError naming the indices of `chosen` outside the plan."""
    bad = [i for i in chosen if not 0 <= i < len(plan)]
    if bad:
        raise SegmentError(f"--segments {','.join(map(str, bad))}: the {num_frames}-frame video has "
                           f"{len(plan)} segment{'s' if len(plan) > 1 else ''} of {segment_frames} frames "
                           f"(indices 0-{len(plan) - 1})")


def prepare_segments(dataset, out: Path, segment_frames: int, indices: Sequence[int] | None, resume: bool,
                     quiet: bool = False, context: int = 0):
    """The segments of a run before any is trained: (dataset with its frame cache cut at the segments
    and their `context` frames (segments.cache_chunks), plan, indices to train). Checks the indices, OUT (creating it) and OUT's plan (SegmentError), removes leftovers of
    killed writes, and without `resume` the marks of finished segments of the chosen ones (so they
    are trained afresh); with it, says which finished segments are kept."""
    plan = plan_segments(dataset.num_frames, segment_frames)
    chosen = list(range(len(plan))) if indices is None else sorted(set(indices))
    _check_indices(chosen, plan, dataset.num_frames, segment_frames)
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
    return dataset.chunked(cache_chunks(plan, context)), plan, todo


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
                            "warm": bool(m.get("warm", False)),
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
        settings = f"--iterations {config.iterations}" + (f" --model {config.model}" if config.model != "full" else "")
        print(missing_message(out, plan, missing, segment_frames, dataset.path, settings), file=sys.stderr)
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


#: How far check_cameras lets a refined training camera be from the dataset's (of the rig's size in
#: position, radians in rotation).
REFINED_TOLERANCE = 0.05


def check_cameras(player: Player, dataset, name, tolerance: float = 1e-3) -> None:
    """DataError naming the model and the first camera that differs when the model's stored cameras are
    not the dataset's (same names; poses within `tolerance` of the rig's size in position and
    `tolerance` radians; the same focal length relative to the image width, so another --downscale
    still matches). A model that stores no cameras passes. A model trained with pose refinement (its
    provenance says so) stores refined training cameras: those may differ by up to REFINED_TOLERANCE."""
    stored = {c.name: c for c in player.cameras}
    settings = (getattr(player.model, "provenance", None) or {}).get("settings") or {}
    refined = set(dataset.train_cameras) if settings.get("pose_refine") else set()
    if not stored:
        return
    cams = dataset.cameras
    centres = np.stack([c.center for c in cams])
    scale = max(float(np.linalg.norm(centres - centres.mean(0), axis=1).max()), 1e-6)
    hint = "pass --any-cameras to evaluate anyway"
    for i in sorted(set(dataset.test_cameras) | set(dataset.train_cameras)):
        cam = cams[i]
        other = stored.get(cam.name)
        if other is None:
            raise DataError(f"{name}: was not trained on this dataset: it stores no camera {cam.name!r} (it has "
                            f"{', '.join(sorted(stored)[:6])}{', ...' if len(stored) > 6 else ''}); {hint}")
        moved = float(np.linalg.norm(cam.center - other.center)) / scale
        turned = float(np.abs(cam.R - other.R).max())
        focal = abs(cam.fx / cam.width - other.fx / other.width) / (cam.fx / cam.width)
        limit = max(tolerance, REFINED_TOLERANCE) if i in refined else tolerance
        if moved > limit or turned > limit or focal > tolerance or cam.model != other.model:
            raise DataError(f"{name}: was not trained on this dataset: its camera {cam.name!r} differs from the "
                            f"dataset's (position off by {moved:.3g} of the rig's size, rotation by {turned:.3g}, "
                            f"focal length by {100 * focal:.3g}%); {hint}")


def align_heldout(player: Player, dataset, frames: Sequence[int], quiet: bool = False):
    """(dataset with each held-out camera's pose aligned to its pictures, {camera name: PoseAlignment}):
    pose_align.align_view against the model `player` plays, on ALIGN_FRAMES of `frames` (dataset frame
    indices), the shift counted in units of the scene's depth (data.bounds.typical_depth of the training
    cameras; their extent, params.extent_of, where the dataset has no bounds). For a held-out camera
    calibrated no better than the training cameras, or a model whose refined poses moved its frame:
    the view is then scored on what the model shows rather than on where the calibration puts it. A
    progress bar on stderr unless quiet."""
    from stg_runtime.progress import Progress

    from .data.bounds import typical_depth
    from .params import extent_of
    from .rig.pose_align import ALIGN_FRAMES, align_view, renders_at_most

    train = [dataset.cameras[i] for i in dataset.train_cameras]
    depth = typical_depth(None if dataset.bounds is None else dataset.bounds[dataset.train_cameras]) or extent_of(train)
    start = getattr(dataset, "start_frame", 0)
    cameras, moved = list(dataset.cameras), {}
    budget = renders_at_most(min(ALIGN_FRAMES, len(frames)))  # a camera's share of the bar
    with Progress(total=len(dataset.test_cameras) * budget, desc="aligning the held-out poses",
                  enabled=not quiet) as bar:
        def render(camera, j):
            bar.update()
            return player.render(camera, (start + j) / dataset.fps)

        for k, ci in enumerate(dataset.test_cameras):
            result = align_view(render, cameras[ci], lambda j: dataset.image(ci, j), frames, depth)
            cameras[ci], moved[cameras[ci].name] = result.camera, result
            bar.update((k + 1) * budget - bar.count)  # the renders an early stop saved
    return dataset.with_cameras(cameras), moved


def run_demo(out, config: TrainConfig, resume: bool = False, quiet: bool = False, check: bool = True,
             segment_frames: int | None = None, segments: Sequence[int] | None = None, callback=None,
             given: dict[str, str] | None = None, stop_on_signal: bool = False) -> dict:
    """The demo: the synthetic scene written into OUT/data (once), trained with `config`, and a
    novel-view video OUT/orbit.mp4 along an orbit around the training cameras; returns the metrics (no
    video while segments are missing)."""
    out = Path(out)
    data = ensure_demo_scene(out / "data", announce=not quiet)
    dataset = load_dataset(data, show_progress=not quiet, lazy=True)
    metrics = train(dataset, out, config, resume, quiet, check, segment_frames, segments, callback=callback,
                    given=given, stop_on_signal=stop_on_signal)
    if metrics.get("missing_segments"):
        return metrics  # OUT/model.stg waits for the other segments (train_segments said which)
    player = Player(out / "model.stg", device="cpu")
    path = orbit([dataset.cameras[i] for i in dataset.train_cameras], dataset.num_frames)
    player.render_video(out / "orbit.mp4", path, times=np.arange(dataset.num_frames) / dataset.fps,
                        progress=not quiet)
    return metrics
