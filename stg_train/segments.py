"""Long videos: train consecutive time segments as independent models and merge them into one file.

A video of F frames is cut into segments of `segment_frames` frames (the paper's 50); a last piece
shorter than half a segment joins the segment before it, so no segment is a near-static sliver. Each
segment is an ordinary training run on a frame-range view of the dataset (Dataset.frame_range), in its
own folder OUT/segments/NN/ (checkpoint.pt, model.stg starting at its start_frame, metrics.json), with
time normalised over the segment (frame j of a segment of n frames has tau = j / n). When every segment
of the plan is finished, their files are merged (stg_train.convert.merge) into OUT/model.stg, which the
Player plays end to end, and the held-out camera is evaluated over every frame.

A segment is finished when its folder holds metrics.json (written last, after export and evaluation)
and a model.stg covering its frames. `--segments` trains a subset (segments can run on several machines
into copies of OUT and be gathered into one OUT/segments/ afterwards); `--resume` skips finished
segments and continues an unfinished one from its checkpoint. OUT/segments/plan.json records the cut,
so runs into one OUT cannot mix segment lengths.
"""
from __future__ import annotations

import json
import os
import sys
from dataclasses import asdict
from pathlib import Path
from typing import NamedTuple, Sequence

PLAN_NAME = "plan.json"


class SegmentError(Exception):
    """Bad segment settings or inconsistent segment folders; the message says what and where."""


class Span(NamedTuple):
    """Segment `index` covers frames [start, start + count) of the video."""

    index: int
    start: int
    count: int

    def frames(self) -> str:
        return f"frames {self.start}-{self.start + self.count - 1}"


def plan_segments(num_frames: int, segment_frames: int) -> list[Span]:
    """Cut num_frames frames into consecutive spans of segment_frames frames; a last span shorter than
    half of segment_frames is merged into the one before it."""
    if num_frames <= 0 or segment_frames <= 0:
        raise ValueError(f"plan_segments: need positive counts, got {num_frames} frames, {segment_frames} per segment")
    starts = list(range(0, num_frames, segment_frames))
    if len(starts) > 1 and 2 * (num_frames - starts[-1]) < segment_frames:
        starts.pop()
    ends = starts[1:] + [num_frames]
    return [Span(i, s, e - s) for i, (s, e) in enumerate(zip(starts, ends))]


def parse_segment_list(text: str) -> list[int]:
    """"2,3" / "0-2" / "0-2,5" -> sorted distinct segment indices (counted from 0). Raises ValueError."""
    out = set()
    for part in text.replace(" ", "").split(","):
        if not part:
            continue
        lo, sep, hi = part.partition("-")
        if not lo.isdigit() or (sep and not hi.isdigit()):
            raise ValueError(f"segment list {text!r}: {part!r} is not an index or a range like 0-2")
        a, b = int(lo), int(hi) if sep else int(lo)
        if b < a:
            raise ValueError(f"segment list {text!r}: range {part!r} runs backwards")
        out.update(range(a, b + 1))
    if not out:
        raise ValueError(f"segment list {text!r} names no segment")
    return sorted(out)


def segment_dir(out, index: int, count: int) -> Path:
    """OUT/segments/NN: two digits, more when there are 100 or more segments (so names sort in time order)."""
    return Path(out) / "segments" / f"{index:0{max(2, len(str(count - 1)))}d}"


def _check_plan(out: Path, plan: list[Span], segment_frames: int) -> None:
    """Record the plan in OUT/segments/plan.json, or refuse when OUT already holds another cut."""
    path = out / "segments" / PLAN_NAME
    wanted = {"num_frames": sum(s.count for s in plan), "segment_frames": segment_frames,
              "segments": [[s.start, s.count] for s in plan]}
    if path.exists():
        try:
            found = json.loads(path.read_text())
        except (OSError, ValueError) as e:
            raise SegmentError(f"{path}: unreadable ({e}); delete it if OUT/segments holds no segments") from None
        if found != wanted:
            raise SegmentError(f"{path}: OUT holds segments of a {found.get('num_frames')}-frame video cut every "
                               f"{found.get('segment_frames')} frames, this run cuts {wanted['num_frames']} frames "
                               f"every {segment_frames}: use the same --segment-frames and data, or another --out")
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f"{PLAN_NAME}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(wanted) + "\n")
    os.replace(tmp, path)


def finished(folder: Path, span: Span) -> bool:
    """Whether `folder` holds a finished segment covering `span` (metrics.json and a matching model.stg)."""
    from stg_runtime import format as stg_format

    if not (folder / "metrics.json").exists() or not (folder / "model.stg").exists():
        return False
    try:
        model = stg_format.load(folder / "model.stg")
    except (OSError, ValueError):
        return False
    return (model.start_frame, model.num_frames) == (span.start, span.count)


def _pooled(results: Sequence[dict]) -> dict:
    """One evaluate_player-style summary of several (means weighted by their image counts)."""
    images = sum(r["images"] for r in results)
    out = {k: float(sum(r[k] * r["images"] for r in results) / images) for k in ("psnr", "ssim", "dssim1", "dssim2")}
    seconds = sum(r["images"] / r["fps"] for r in results if r["fps"] > 0)
    cameras = sorted({c for r in results for c in r["cameras"]})
    return {**out, "fps": images / seconds if seconds > 0 else float("inf"), "images": images, "cameras": cameras}


def train_segments(dataset, out, config, segment_frames: int, indices: Sequence[int] | None = None,
                   resume: bool = False, quiet: bool = False, check: bool = True) -> dict:
    """Train the segments `indices` (default: all) of `dataset` cut every segment_frames frames into
    OUT/segments/NN, then merge every segment into OUT/model.stg when all are finished, evaluate and
    write OUT/metrics.json; returns the metrics ("missing_segments" lists the indices still to train).

    resume: keep finished segments and continue an unfinished one from its checkpoint; otherwise the
    chosen segments are trained afresh. Raises SegmentError for indices outside the plan or an OUT
    cut differently, DataError for bad data (from the training runs).
    """
    from stg_runtime.player import Player

    from .cli import run_training
    from .convert.merge import merge_files
    from .metrics import evaluate_player

    out = Path(out)
    plan = plan_segments(dataset.num_frames, segment_frames)
    chosen = list(range(len(plan))) if indices is None else sorted(set(indices))
    bad = [i for i in chosen if not 0 <= i < len(plan)]
    if bad:
        raise SegmentError(f"--segments {','.join(map(str, bad))}: the {dataset.num_frames}-frame video has "
                           f"{len(plan)} segment{'s' if len(plan) > 1 else ''} of {segment_frames} frames "
                           f"(indices 0-{len(plan) - 1})")
    _check_plan(out, plan, segment_frames)
    folders = [segment_dir(out, s.index, len(plan)) for s in plan]
    for i in chosen:
        span, folder = plan[i], folders[i]
        if resume and finished(folder, span):
            if not quiet:
                print(f"segment {i} ({span.frames()}): finished, keeping {folder / 'model.stg'}", file=sys.stderr)
            continue
        if not resume:
            for name in ("metrics.json", "model.stg"):  # the marks of a finished segment
                (folder / name).unlink(missing_ok=True)
        if not quiet:
            print(f"segment {i} of 0-{len(plan) - 1} ({span.frames()}) -> {folder}", file=sys.stderr)
        run_training(dataset.frame_range(span.start, span.count), folder, config, resume, quiet, check)

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
        heldout = evaluate_player(Player(model_path, device="cpu"), dataset)
        file_bytes = model_path.stat().st_size
    else:  # the finished segments' own evaluations (of the same files, over their frames), pooled
        heldout = _pooled(heldouts)
        file_bytes = sum(p["file_bytes"] for p in per_segment)
        print(missing_message(out, plan, missing, segment_frames, dataset.path), file=sys.stderr)
    metrics = {"heldout": {k: heldout[k] for k in ("psnr", "ssim", "dssim1", "dssim2", "fps", "images", "cameras")},
               "model": None if model_path is None else str(model_path),
               "segment_frames": segment_frames, "segments": per_segment,
               "missing_segments": [s.index for s in missing],
               "iterations": sum(p["iterations"] for p in per_segment),
               "train_seconds": sum(p["train_seconds"] for p in per_segment),
               "gaussians": sum(p["gaussians"] for p in per_segment), "file_bytes": file_bytes,
               "export_check": _worst_check(per_segment), "settings": asdict(config)}
    tmp = out / "metrics.json.tmp"
    tmp.write_text(json.dumps(metrics, indent=1) + "\n")
    tmp.replace(out / "metrics.json")
    return metrics


def _worst_check(per_segment: list[dict]) -> dict | None:
    checks = [p["export_check"] for p in per_segment if p["export_check"]]
    if not checks:
        return None
    return {"max_abs": max(c["max_abs"] for c in checks), "fraction_over": max(c["fraction_over"] for c in checks)}


def missing_message(out: Path, plan: list[Span], missing: list[Span], segment_frames: int, data=None) -> str:
    """What is missing for OUT/model.stg, and how to finish it."""
    idx = ",".join(str(s.index) for s in missing)
    listing = ", ".join(f"{s.index} ({s.frames()})" for s in missing)
    cmd = f"stg-train {data or 'DATA'} --out {out} --segment-frames {segment_frames}"
    return (f"stg-train: {out / 'model.stg'} not written: segment{'s' if len(missing) > 1 else ''} {listing} "
            f"of {len(plan)} not trained yet. Train {'them' if len(missing) > 1 else 'it'} with "
            f"`{cmd} --segments {idx}` (on any machine; copy the folders into {out / 'segments'}/), then "
            f"`{cmd} --resume` merges and evaluates without retraining, or merge by hand with "
            f"`stg-convert merge {out / 'segments'}/*/model.stg {out / 'model.stg'}`.")
