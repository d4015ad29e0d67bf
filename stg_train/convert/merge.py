"""Merge `.stg` files whose segments follow each other into one file (numpy only, no torch).

Segments trained separately (`stg-train --segments ...`, on one machine or several) are independent
models, so merging is concatenation: every input's segments, sorted by start_frame, must be
consecutive without gaps or overlaps, and the inputs must share kind and fps. Where two neighbouring
segments were both fitted to frames beyond the seam (context_frames, TrainConfig.segment_context), the
merged file crossfades them over the seam (seam_crossfade). The merged file keeps the
inputs' attribute encodings where they all agree (one encoding per attribute for the whole file;
re-encoding a u8 / u16 attribute with its own encoding moves values by at most ~1% of a quantization
step) and stores float32 otherwise; cameras are the union of the inputs' cameras, bounds the union of
their boxes, and the provenance lists the sources.
"""
from __future__ import annotations

import json
import os
from dataclasses import replace
from typing import Sequence

import numpy as np

import stg_runtime
from stg_runtime import format as stg_format
from stg_runtime.format import FormatError
from stg_runtime.model import ATTRIBUTES, Model, Segment

TOOL = "stg-convert merge"


def _frames(start: int, count: int) -> str:
    return f"frame {start}" if count == 1 else f"frames {start}-{start + count - 1}"


def _span(model: Model) -> tuple[int, int]:
    return model.start_frame, model.start_frame + model.num_frames


def seam_crossfade(before: Segment, after: Segment, crossfade: int | None = None) -> int:
    """The crossfade_frames of the seam between consecutive segments `before` and `after`: at most what
    their context allows (the window reaches b / 2 frames into each neighbour, so b <= 2 x the smaller
    of before's context after it and after's context before it) and at most either one's frame count.
    crossfade None: the context frames both have (b = that smaller context: the window stays in the
    inner half of the context); 0: a hard cut."""
    shared = min(before.context_frames[1], after.context_frames[0])
    wanted = shared if crossfade is None else min(int(crossfade), 2 * shared)
    return max(0, min(wanted, before.num_frames, after.num_frames))


def merge_models(models: Sequence[Model], names: Sequence[str] | None = None, crossfade: int | None = None) -> Model:
    """One Model holding the segments of `models` in time order, every seam crossfaded as far as its
    segments' context allows (seam_crossfade; `crossfade` as there).

    names: one label per model for messages and provenance (default "input 0", "input 1", ...).
    Raises ValueError naming the inputs (and frames) when kinds or fps differ, or when the segments,
    sorted by start_frame, leave a gap or overlap. Segments share their arrays with the inputs.
    """
    models = list(models)
    names = [f"input {i}" for i in range(len(models))] if names is None else [str(n) for n in names]
    if len(names) != len(models):
        raise ValueError(f"merge: {len(models)} models but {len(names)} names")
    if not models:
        raise ValueError("merge: no models to merge")
    first = models[0]
    for name, m in zip(names[1:], models[1:]):
        if m.kind != first.kind:
            raise ValueError(f"merge: kind mismatch: {names[0]} is a {first.kind} model, {name} is {m.kind}")
        if abs(m.fps - first.fps) > 1e-9 * first.fps:
            raise ValueError(f"merge: fps mismatch: {names[0]} has {first.fps:g} fps, {name} has {m.fps:g}")
    pieces = sorted(((seg.start_frame, i, seg) for i, m in enumerate(models) for seg in m.segments),
                    key=lambda p: (p[0], p[1]))
    for (s0, i0, a), (s1, i1, b) in zip(pieces, pieces[1:]):
        end = a.start_frame + a.num_frames
        if s1 < end:
            shared = _frames(s1, min(end, s1 + b.num_frames) - s1)
            raise ValueError(f"merge: {names[i0]} ({_frames(s0, a.num_frames)}) and {names[i1]} "
                             f"({_frames(s1, b.num_frames)}) overlap at {shared}")
        if s1 > end:
            verb = "is" if s1 - end == 1 else "are"
            raise ValueError(f"merge: gap: {_frames(end, s1 - end)} {verb} in no input (between {names[i0]}, "
                             f"{_frames(s0, a.num_frames)}, and {names[i1]}, {_frames(s1, b.num_frames)})")
    cameras = []
    seen = set()
    for m in models:
        for cam in m.cameras:
            key = json.dumps(cam.to_dict(), sort_keys=True)
            if key not in seen:
                seen.add(key)
                cameras.append(cam)
    boxes = [np.asarray(m.bounds, np.float64).reshape(2, 3) for m in models if m.bounds is not None]
    bounds = None
    if boxes:
        bounds = (tuple(np.min([b[0] for b in boxes], 0).tolist()), tuple(np.max([b[1] for b in boxes], 0).tolist()))
    sources = [{"name": n, "start_frame": m.start_frame, "num_frames": m.num_frames, "provenance": m.provenance}
               for n, m in sorted(zip(names, models), key=lambda p: p[1].start_frame)]
    provenance = {"tool": TOOL, "version": stg_runtime.__version__, "sources": sources}
    segments = [p[2] for p in pieces]
    fades = [0] + [seam_crossfade(a, b, crossfade) for a, b in zip(segments, segments[1:])]
    segments = [seg if seg.crossfade_frames == fade else replace(seg, crossfade_frames=fade)
                for seg, fade in zip(segments, fades)]
    return Model(first.kind, first.fps, segments, cameras=cameras, bounds=bounds, provenance=provenance)


def attribute_encodings(path) -> dict[str, set[str]]:
    """attribute name -> the encodings its segments use in the .stg file `path` (read from the header,
    as format.save's encoding strings: "u16", "u16-delta:3+u8:9", ...; the file should already have
    passed stg_runtime.format.load)."""
    with open(path, "rb") as f:
        prefix = f.read(stg_format.PREFIX.size)
        _, _, _, length = stg_format.PREFIX.unpack(prefix)
        header = json.loads(f.read(length).decode("utf-8"))
    found: dict[str, set[str]] = {}
    for seg in header["segments"]:
        for name, spec in seg["attributes"].items():
            if name in ATTRIBUTES:  # unknown attributes (a newer file's) are not read
                found.setdefault(name, set()).add(stg_format.encoding_of(spec))
    return found


def merge_files(paths: Sequence, out_path, provenance: dict | None = None, crossfade: int | None = None) -> Model:
    """Merge the .stg files `paths` into `out_path` (written atomically) and return the merged Model
    (crossfade: as merge_models).

    provenance: keys that replace or extend the merged provenance (tool, version, sources). Raises
    FormatError naming a file that is not a valid .stg file, ValueError naming an unreadable file or
    inputs that do not fit together (see merge_models); nothing is written then.
    """
    paths = [os.fspath(p) for p in paths]
    if not paths:
        raise ValueError("merge: no input files")
    models, encodings = [], {}
    for path in paths:
        try:
            models.append(stg_format.load(path))
            found = attribute_encodings(path)
        except FormatError:
            raise
        except OSError as e:
            raise ValueError(f"{path}: cannot read ({e.strerror or e})") from None
        for name, used in found.items():
            encodings.setdefault(name, set()).update(used)
    model = merge_models(models, names=paths, crossfade=crossfade)
    if provenance:
        model.provenance.update(provenance)
    keep = {name: next(iter(used)) for name, used in encodings.items() if name in ATTRIBUTES and len(used) == 1}
    stg_format.save(model, out_path, encodings=keep)
    return model
