"""Is DATA and OUT the same storage on every node? The check a cluster run makes before any job starts.

The driver writes a marker file with a random token into OUT/segments and lists what every node must
see: DATA's folder and, for each camera, its first and last source file with their sizes; OUT's
marker with its token; a writable frame-cache folder. `node_problems` runs on each node and returns
what it does not see (a node that mounts another disk at the same path sees OUT but not the token).
"""
from __future__ import annotations

import os
import secrets
from pathlib import Path

from stg_runtime.atomic import write_atomic

MARKER_PREFIX = ".shared-storage-"


def write_marker(out: Path) -> tuple[Path, str]:
    """A new marker file in OUT/segments holding a random token: (its path, the token)."""
    token = secrets.token_hex(8)
    path = Path(out) / "segments" / f"{MARKER_PREFIX}{token}"
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(path, token)
    return path, token


def expectations(dataset, marker: Path, token: str) -> dict:
    """What every node must see of `dataset` (its folder and frame sources, its frame cache) and of OUT
    (the marker): a JSON-able dict for node_problems."""
    files = []
    frames = dataset.frames
    decoder = getattr(frames, "decoder", None)
    if decoder is not None:
        for source in decoder.sources:
            for f in {source.files[0], source.files[-1]}:
                files.append([str(f), Path(f).stat().st_size])
    cache = str(frames.cache_dir.parent) if decoder is not None else None
    return {"data": str(dataset.path) if dataset.path is not None else None, "files": files,
            "marker": [str(marker), token], "cache": cache}


def node_problems(expected: dict) -> list[str]:
    """What this machine does not see of `expected` (expectations): one line per problem, [] when all
    is there. Creates the frame-cache folder when it is missing."""
    problems = []
    data = expected.get("data")
    if data is not None and not Path(data).is_dir():
        problems.append(f"DATA {data}: no such directory")
    else:
        for name, size in expected["files"]:
            try:
                found = os.stat(name).st_size
            except OSError as e:
                problems.append(f"DATA file {name}: cannot be read ({e.strerror or e})")
                break
            if found != size:
                problems.append(f"DATA file {name}: {found} bytes here, {size} on the driver")
                break
    marker, token = expected["marker"]
    try:
        seen = Path(marker).read_text()
    except OSError as e:
        problems.append(f"OUT {Path(marker).parent.parent}: the driver's marker {Path(marker).name} cannot be read "
                        f"({e.strerror or e})")
    else:
        if seen != token:
            problems.append(f"OUT {Path(marker).parent.parent}: the marker {Path(marker).name} holds another token")
    cache = expected.get("cache")
    if cache is not None:
        try:
            Path(cache).mkdir(parents=True, exist_ok=True)
            probe = Path(cache) / f"{MARKER_PREFIX}{secrets.token_hex(4)}"
            probe.write_bytes(b"")
            probe.unlink()
        except OSError as e:
            problems.append(f"frame cache {cache}: not writable ({e.strerror or e})")
    return problems


def unshared_message(problems: dict[str, list[str]]) -> str | None:
    """The error of a check: problems {node name: node_problems(...)} -> a message, None when all is shared."""
    bad = {node: p for node, p in problems.items() if p}
    if not bad:
        return None
    lines = [f"  node {node}: {'; '.join(p)}" for node, p in sorted(bad.items())]
    return ("DATA and OUT must be on storage that every node of the cluster sees at the same path (a shared "
            "file system such as NFS, Lustre or a cloud file store); not every node does:\n" + "\n".join(lines)
            + "\nPut DATA and OUT on the shared storage (or mount it on these nodes) and start again.")
