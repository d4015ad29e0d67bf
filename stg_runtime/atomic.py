"""Atomic file writes: readers see the old file or the whole new one, never a part.

    write_atomic(path, payload)          bytes or str into `path`
    with atomic_output(path) as tmp:     for writers that take a path (torch.save, numpy, OpenCV):
        write(tmp)                       write `tmp`; it becomes `path` when the block ends without error

Both write a temporary file in the same folder, fsync it and rename it over `path`; on any error the
temporary file is removed and `path` is left as it was. Temporary files are named
`.<stem>.<8 hex digits>.tmp<suffix>` (hidden, recognisable by TEMPORARY_PATTERN, suffix kept for
libraries that choose a container by it), so that one left behind by a killed process can be found:
remove_leftovers(folder) deletes them, and every writer of this project calls it when a run starts
writing into a folder (a run's output folder, a cache folder, a render's frames).
"""
from __future__ import annotations

import os
import re
import secrets
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

#: The names temporary_path makes (a match is a leftover of an interrupted write); groups: the target's
#: stem and suffix.
TEMPORARY_PATTERN = re.compile(r"^\.(.*)\.[0-9a-f]{8}\.tmp(\.[^.]*)?$")


def temporary_path(path) -> Path:
    """A new temporary name beside `path`: .<stem>.<8 hex digits>.tmp<suffix>."""
    path = Path(path)
    return path.with_name(f".{path.stem}.{secrets.token_hex(4)}.tmp{path.suffix}")


def remove_leftovers(folder, name: str | None = None) -> int:
    """Delete the temporary files of interrupted writes in `folder` (of the file called `name` only,
    when given); returns how many. A folder that does not exist holds none."""
    removed = 0
    try:
        entries = list(os.scandir(folder))
    except (FileNotFoundError, NotADirectoryError):
        return 0
    for entry in entries:
        match = TEMPORARY_PATTERN.match(entry.name)
        if match and (name is None or match.group(1) + (match.group(2) or "") == name) and entry.is_file():
            Path(entry.path).unlink(missing_ok=True)
            removed += 1
    return removed


def _fsync(path: Path) -> None:
    with open(path, "rb+") as f:
        os.fsync(f.fileno())


@contextmanager
def atomic_output(path) -> Iterator[Path]:
    """Yield a temporary path beside `path`; when the block ends without error the file written there is
    fsynced and renamed to `path`, otherwise it is removed (see the module docstring)."""
    path = Path(path)
    tmp = temporary_path(path)
    try:
        yield tmp
        _fsync(tmp)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_atomic(path, payload: bytes | str) -> None:
    """Write `payload` (bytes, or str as UTF-8) to `path` atomically (see the module docstring)."""
    data = payload.encode("utf-8") if isinstance(payload, str) else payload
    with atomic_output(path) as tmp:
        with open(tmp, "xb") as f:
            f.write(data)
