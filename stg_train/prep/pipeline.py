"""`prepare`: raw videos -> a prepared rig folder (stg_train.prep.write), in five stages: check the inputs
(inputs), read every clip once (the synchronisation signals and the frames of each camera's static
picture), synchronise (sync), calibrate (calibrate), write. Everything is written into a temporary
sibling of OUT, renamed to OUT at the end: a failed run leaves OUT as it was."""
from __future__ import annotations

import inspect
import os
import shutil
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Callable, Mapping, Sequence

import numpy as np

from .calibrate import CAMERA_MODELS, STATIC_FRAMES, calibrate, static_picture
from .inputs import MIN_FRAMES, Clip, PrepError, check_clips, find_clips, source_signature
from .sync import LOW_CONFIDENCE, Offset, SignalMeter, estimate_offsets
from .write import read_report, write_frames, write_model, write_report

#: prep.json's "format".
FORMAT = "stg-prep 1"
#: Stages, in order, as the report's "seconds" and the progress bars name them.
STAGES = ("check", "read", "sync", "calibrate", "write")


def _check_out(videos: Path, out: Path, force: bool) -> None:
    if out.exists() and not out.is_dir():
        raise PrepError(f"{out}: is a file, not a folder")
    if out.resolve() == videos.resolve() or videos.resolve() in out.resolve().parents:
        raise PrepError(f"{out}: inside the folder of videos {videos}; write it elsewhere")
    if out.is_dir() and any(out.iterdir()) and not force:
        raise PrepError(f"{out}: exists and is not empty; choose another OUT or add --force to replace it")


def resolve_offsets(given, clips: list[Clip]) -> list[int]:
    """Offsets given by hand -> one per clip: a sequence of ints in the cameras' (name) order, or a
    mapping name -> int where unnamed cameras get 0. PrepError for an unknown camera, a wrong count, a
    negative offset or one at or past the clip's end."""
    names = [c.name for c in clips]
    if isinstance(given, Mapping):
        unknown = [n for n in given if n not in names]
        if unknown:
            raise PrepError(f"--offsets: no camera {unknown[0]} (the cameras: {', '.join(names)})")
        values = [int(given.get(n, 0)) for n in names]
    else:
        values = [int(v) for v in given]
        if len(values) != len(names):
            raise PrepError(f"--offsets: {len(values)} offsets for {len(names)} cameras ({', '.join(names)})")
    for clip, v in zip(clips, values):
        if not 0 <= v < clip.count:
            raise PrepError(f"{clip.name}: offset {v} outside its {clip.count} frames")
    return values


def _read(clips: list[Clip], signals: bool, progress) -> tuple[list[Clip], list[np.ndarray], dict, list[str]]:
    """One pass over every clip: (the clips, with the frame counts their videos decode; their signals
    (when `signals`); their static pictures; notes on videos that hold fewer frames than they state)."""
    total, done = sum(c.count for c in clips), 0
    out_clips, out_signals, pictures, notes = [], [], {}, []
    for clip in clips:
        keep = set(np.linspace(0, clip.count - 1, min(STATIC_FRAMES, clip.count)).round().astype(int).tolist())
        meter, kept, decoded = SignalMeter(), [], 0
        for k, rgb in enumerate(clip.read(strict=False)):
            if signals:
                meter.add(rgb)
            if k in keep:
                kept.append(rgb)
            decoded, done = k + 1, done + 1
            progress(done, total)
        if decoded < clip.count:
            notes.append(f"{clip.path}: states {clip.count} frames, {decoded} decode; using {decoded}")
            clip = replace(clip, count=decoded)
        if not kept:
            raise PrepError(f"{clip.path}: no frame decodes")
        out_clips.append(clip)
        out_signals.append(meter.signal())
        pictures[clip.name] = static_picture(kept)
    return out_clips, out_signals, pictures, notes


def _common_span(clips: list[Clip], offsets: list[int], min_frames: int) -> tuple[int, list[str]]:
    """(frames every camera has from its offset on, notes on what each camera loses at either end)."""
    span = min(c.count - o for c, o in zip(clips, offsets))
    if span < min_frames:
        short = min(zip(clips, offsets), key=lambda co: co[0].count - co[1])
        raise PrepError(f"{short[0].path}: only {span} frames from offset {short[1]} on, too short: at least "
                        f"{min_frames} are needed in the span common to all cameras")
    notes = []
    for clip, o in zip(clips, offsets):
        if o or clip.count - o > span:
            notes.append(f"{clip.name}: frames {o}-{o + span - 1} of its {clip.count} kept ({o} left out at the "
                         f"start, {clip.count - o - span} at the end)")
    return span, notes


def prepare(videos, out, *, offsets=None, camera_model: str = "pinhole", fps: float | None = None,
            max_offset: int | None = None, min_frames: int = MIN_FRAMES, force: bool = False, threads: int = -1,
            progress: Callable[[str], Callable[[int, int], None]] | None = None) -> dict:
    """Prepare the folder of raw videos `videos` (stg_train.prep.inputs) into the rig folder `out`
    (stg_train.prep.write) and return its report (also out/prep.json).

    offsets: per-camera frame offsets given by hand (resolve_offsets), else estimated (stg_train.prep.sync)
    within max_offset frames (default a third of the shortest clip); camera_model: "pinhole", "opencv"
    or "fisheye" (stg_train.prep.calibrate); fps: the frame rate of frame folders (default the videos',
    else 30); min_frames: the shortest clip, and common span, accepted; force: replace a non-empty out;
    threads: pycolmap's CPU threads (-1: all); progress(stage) -> report(done, total), a callback per
    stage (stg_runtime.progress.progress_stages). PrepError, out untouched, for every problem.
    """
    if camera_model not in CAMERA_MODELS:
        raise ValueError(f"camera_model must be one of {', '.join(CAMERA_MODELS)}, got {camera_model!r}")
    stage = progress or (lambda name: lambda done, total: None)
    videos, out = Path(videos), Path(out)
    seconds, start = {}, time.perf_counter()
    clips = find_clips(videos)
    rate = check_clips(clips, videos, fps, min_frames)
    _check_out(videos, out, force)
    given = resolve_offsets(offsets, clips) if offsets is not None else None
    seconds["check"] = time.perf_counter() - start
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.prep-", dir=out.parent))
    try:
        record = _options_record(dict(offsets=offsets, camera_model=camera_model, fps=fps, max_offset=max_offset,
                                      min_frames=min_frames))
        report = _prepare_into(tmp, videos, clips, rate, given, camera_model, max_offset, min_frames, threads,
                               stage, seconds, record)
        _replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return report


def _prepare_into(tmp: Path, videos: Path, clips: list[Clip], fps: float, given, camera_model: str,
                  max_offset, min_frames: int, threads: int, stage, seconds: dict, record: dict) -> dict:
    t = time.perf_counter()
    clips, signals, pictures, warnings = _read(clips, given is None, stage("stg-prep read"))
    seconds["read"], t = time.perf_counter() - t, time.perf_counter()
    if given is None:
        shortest = min(c.count for c in clips)
        limit = shortest // 3 if max_offset is None else min(int(max_offset), shortest - min_frames)
        found = estimate_offsets(signals, max(limit, 0))
    else:
        limit, found = None, [Offset(v, None) for v in given]
    offsets = [o.frames for o in found]
    span, trimmed = _common_span(clips, offsets, min_frames)
    warnings += [f"{c.name}: offset {o.frames} found with a low confidence {o.confidence:.2f} (below "
                f"{LOW_CONFIDENCE}); check it, or give the offsets with --offsets"
                for c, o in zip(clips, found) if o.confidence is not None and o.confidence < LOW_CONFIDENCE]
    seconds["sync"], t = time.perf_counter() - t, time.perf_counter()
    calibration = calibrate(pictures, tmp / ".work", camera_model, threads, progress=stage)
    if calibration.fallback:
        warnings.append(f"camera model {calibration.fallback}")
    seconds["calibrate"], t = time.perf_counter() - t, time.perf_counter()
    write_frames(tmp, clips, offsets, span, calibration.cameras, calibration.distortion, stage("stg-prep write"))
    write_model(tmp, calibration.cameras, calibration.points, calibration.colours)
    shutil.rmtree(tmp / ".work", ignore_errors=True)
    seconds["write"] = time.perf_counter() - t
    report = _report(videos, clips, fps, offsets, found, span, trimmed, limit, calibration, camera_model,
                     warnings, seconds)
    report["options"] = record
    write_report(tmp, report)
    return report


def _report(videos, clips, fps, offsets, found, span, trimmed, limit, calibration, camera_model, warnings,
            seconds) -> dict:
    cameras = []
    for clip, o, cam in zip(clips, found, calibration.cameras):
        observations, error = calibration.per_camera[clip.name]
        cameras.append({"name": clip.name, "source": str(clip.path), "frames": clip.count, "offset": o.frames,
                        "confidence": None if o.confidence is None else round(o.confidence, 4),
                        "frames_used": [o.frames, o.frames + span - 1], "observations": observations,
                        "reprojection_error_px": round(error, 4), "fx": cam.fx, "fy": cam.fy, "cx": cam.cx,
                        "cy": cam.cy, "distortion": list(calibration.distortion.get(clip.name, cam.distortion))})
    return {
        "format": FORMAT, "source": str(videos.resolve()), "inputs": source_signature(clips),
        "fps": fps, "width": clips[0].width, "height": clips[0].height, "frames": span,
        "sync": {"method": "estimated" if found[0].confidence is not None else "given", "max_offset": limit,
                 "low_confidence": LOW_CONFIDENCE},
        "trimmed": trimmed,
        "calibration": {"camera_model": calibration.model, "requested": camera_model,
                        "fallback": calibration.fallback, "registered": len(calibration.cameras),
                        "cameras": len(clips), "mean_reprojection_error_px": round(calibration.reprojection_error, 4),
                        "points": int(len(calibration.points)), "intrinsics": calibration.intrinsics,
                        "intrinsics_fits": {k: {"mean_reprojection_error_px": round(e, 4), "observations": n}
                                            for k, (e, n) in calibration.intrinsics_fits.items()}},
        "cameras": cameras, "warnings": warnings,
        "seconds": {k: round(v, 3) for k, v in seconds.items()},
    }


def _replace(tmp: Path, out: Path) -> None:
    """Rename tmp to out; an existing out (checked empty, or --force) is moved aside first and removed."""
    old = None
    if out.exists():
        old = out.with_name(f".{out.name}.old-{os.getpid()}")
        out.rename(old)
    tmp.rename(out)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def prepared(videos, out, announce: Callable[[], None] | None = None, **options) -> tuple[dict, bool]:
    """(report, reused): `out` prepared from `videos` with `options` (prepare's keywords), or reused as it
    is when its prep.json says it was made from the same files with the same options. announce() is
    called before a preparation starts (not when the folder is reused)."""
    report = read_report(out)
    if report is not None and report.get("format") == FORMAT and report.get("options") == _options_record(options):
        if report.get("inputs") == source_signature(find_clips(videos)):
            return report, True
    if announce is not None:
        announce()
    return prepare(videos, out, force=True, **options), False


#: prepare's keywords that decide what it writes (prep.json records them under "options").
RECORDED = ("offsets", "camera_model", "fps", "max_offset", "min_frames")


def _options_record(options: dict) -> dict:
    """The RECORDED options, prepare's defaults where `options` has none, as JSON."""
    defaults = inspect.signature(prepare).parameters
    record = {k: options.get(k, defaults[k].default) for k in RECORDED}
    if isinstance(record["offsets"], Sequence) and not isinstance(record["offsets"], str):
        record["offsets"] = list(record["offsets"])
    return record
