"""Long videos as consecutive segments: the plan (where the video is cut, which folder holds each
segment, which segments are finished) that stg_train.pipeline.train_segments carries out.

A video of F frames is cut into segments of `segment_frames` frames (the paper's 50); a last piece
shorter than half a segment joins the segment before it, so no segment is a near-static sliver. Each
segment is an ordinary training run on a frame-range view of the dataset (Dataset.frame_range), in its
own folder OUT/segments/NN/ (checkpoint.pt, model.stg starting at its start_frame, metrics.json), with
time normalised over the segment (frame j of a segment of n frames has tau = j / n). With
TrainConfig.segment_context = c, a segment is also fitted to up to c frames of each neighbour (its
view's context frames, segment_view; its time is still normalised over its own frames, so the
context frames lie just outside [0, 1), trainer.frame_time, and its file covers its own frames), and
the merge crossfades every seam whose two segments both have context
(stg_train.convert.merge, formats/stg-v1.md "Segments and crossfades"). When every segment
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
from pathlib import Path
from typing import NamedTuple, Sequence

from stg_runtime import format as stg_format
from stg_runtime.atomic import write_atomic

from .metrics import LPIPS_KEYS, REGION_KEYS

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


def context_of(span: Span, num_frames: int, frames: int) -> tuple[int, int]:
    """(before, after): the context frames of `span` in a num_frames-frame video, up to `frames` on
    each side (fewer where the video starts or ends)."""
    return min(frames, span.start), min(frames, num_frames - span.start - span.count)


def segment_view(dataset, span: Span, context: int):
    """The dataset view a segment is trained on: its frames plus up to `context` neighbouring frames on
    each side (Dataset.frame_range with context)."""
    return dataset.frame_range(span.start, span.count, context_of(span, dataset.num_frames, context))


def cache_chunks(plan: Sequence[Span], context: int) -> list[tuple[int, int]]:
    """Frame-cache chunks ((start, count), consecutive) for training `plan` with `context` frames: each
    segment's frames, with the `context` frames at either inner end cut off as chunks of their own, so
    that a segment's view decodes its own frames and only the small chunks of its neighbours' ends."""
    cuts = set()
    for s in plan:
        cuts.update((s.start, s.start + s.count))
        if context and 2 * context < s.count:
            cuts.update((s.start + context, s.start + s.count - context))
    cuts = sorted(cuts)
    return [(a, b - a) for a, b in zip(cuts, cuts[1:])]


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


def check_plan(out: Path, plan: list[Span], segment_frames: int) -> None:
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
    write_atomic(path, json.dumps(wanted) + "\n")


def finished(folder: Path, span: Span) -> bool:
    """Whether `folder` holds a finished segment covering `span` (metrics.json and a matching model.stg)."""
    if not (folder / "metrics.json").exists() or not (folder / "model.stg").exists():
        return False
    try:
        model = stg_format.load(folder / "model.stg")
    except (OSError, ValueError):
        return False
    return (model.start_frame, model.num_frames) == (span.start, span.count)


def pooled(results: Sequence[dict]) -> dict:
    """One evaluate_player-style summary of several (means weighted by their image counts; LPIPS where
    every one has it; the dynamic / static region figures over those that have them)."""
    images = sum(r["images"] for r in results)
    keys = ["psnr", "ssim", "dssim1", "dssim2"] + [k for k in LPIPS_KEYS if all(k in r for r in results)]
    out = {k: float(sum(r[k] * r["images"] for r in results) / images) for k in keys}
    for k in REGION_KEYS:  # each segment's own dynamic mask (over its frames); None where it had none
        have = [r for r in results if r.get(k) is not None]
        out[k] = float(sum(r[k] * r["images"] for r in have) / sum(r["images"] for r in have)) if have else None
    seconds = sum(r["images"] / r["fps"] for r in results if r["fps"] > 0)
    cameras = sorted({c for r in results for c in r["cameras"]})
    return {**out, "fps": images / seconds if seconds > 0 else float("inf"), "images": images, "cameras": cameras}


def worst_check(per_segment: list[dict]) -> dict | None:
    """The worst export check over the segments' metrics (None when none was checked)."""
    checks = [p["export_check"] for p in per_segment if p["export_check"]]
    if not checks:
        return None
    return {"max_abs": max(c["max_abs"] for c in checks), "fraction_over": max(c["fraction_over"] for c in checks)}


def missing_message(out: Path, plan: list[Span], missing: list[Span], segment_frames: int, data=None,
                    settings: str = "") -> str:
    """What is missing for OUT/model.stg, and how to finish it; settings: the run's options that the
    commands must repeat (e.g. "--iterations 3000 --model lite")."""
    idx = ",".join(str(s.index) for s in missing)
    listing = ", ".join(f"{s.index} ({s.frames()})" for s in missing)
    cmd = f"stg-train {data or 'DATA'} --out {out} --segment-frames {segment_frames}{' ' + settings if settings else ''}"
    return (f"stg-train: {out / 'model.stg'} not written: segment{'s' if len(missing) > 1 else ''} {listing} "
            f"of {len(plan)} not trained yet. Train {'them' if len(missing) > 1 else 'it'} with "
            f"`{cmd} --segments {idx}` (on any machine; copy the folders into {out / 'segments'}/), then "
            f"`{cmd} --resume` merges and evaluates without retraining, or merge by hand with "
            f"`stg-convert merge {out / 'segments'}/*/model.stg {out / 'model.stg'}`.")
