"""`export_web`: a self-contained folder that plays a `.stg` model in any browser (docs/web.md).

The folder holds index.html, the player's ES modules (this package's files, shipped as package data)
and the model file, unchanged; nothing is fetched from elsewhere, so it works offline and from any
static host (`python -m http.server` is enough).
"""
from __future__ import annotations

import os
import re
from importlib import resources
from pathlib import Path

from ..atomic import write_atomic
from ..format import DEFAULT_LIMITS, Limits, load

#: The player's files, in the package and in an exported folder.
PLAYER_FILES = ("index.html", "app.js", "player.js", "renderer.js", "shaders.js", "controls.js", "sort-worker.js",
                "stream.js", "stg-format.js", "onnx-mlp.js", "sha256.js")


def player_file(name: str) -> bytes:
    """The bytes of one of PLAYER_FILES."""
    return resources.files(__package__).joinpath(name).read_bytes()


def export_web(model_path, out_dir, limits: Limits = DEFAULT_LIMITS) -> list[Path]:
    """Write OUT_DIR/index.html, the player's modules and a copy of the model (same file name; the page
    opens it). The model is read first (FormatError for a bad file: nothing is written); OUT_DIR is
    created when missing, and each file is written atomically. Returns the written paths."""
    model_path = Path(model_path)
    load(model_path, limits)  # refuse a bad file before writing anything
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise ValueError(f"{out}: not a folder")
    name = model_path.name
    if not re.fullmatch(r"[A-Za-z0-9._-]+", name) or name in PLAYER_FILES:
        name = "model.stg"
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for file in PLAYER_FILES:
        data = player_file(file)
        if file == "index.html":
            data = data.replace(b'content="model.stg"', f'content="{name}"'.encode())
        write_atomic(out / file, data)
        written.append(out / file)
    target = out / name
    if not (target.exists() and os.path.samefile(target, model_path)):
        write_atomic(target, model_path.read_bytes())
    written.append(target)
    return written
