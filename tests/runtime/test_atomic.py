"""stg_runtime.atomic: a reader sees the old file or the whole new one; failures leave nothing behind."""
from __future__ import annotations

import os

import numpy as np
import pytest

from stg_runtime.atomic import TEMPORARY_PATTERN, atomic_output, remove_leftovers, temporary_path, write_atomic


def test_write_atomic_replaces_the_file(tmp_path):
    path = tmp_path / "a.json"
    write_atomic(path, "old")
    write_atomic(path, b"new")
    assert path.read_bytes() == b"new" and os.listdir(tmp_path) == ["a.json"]


def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path):
    path = tmp_path / "model.stg"
    write_atomic(path, b"old")
    with pytest.raises(RuntimeError, match="writer failed"):
        with atomic_output(path) as tmp:
            tmp.write_bytes(b"half")
            raise RuntimeError("writer failed")
    assert path.read_bytes() == b"old" and os.listdir(tmp_path) == ["model.stg"]
    with pytest.raises(FileNotFoundError):
        with atomic_output(tmp_path / "new.npz"):
            pass  # the writer wrote nothing: the rename fails, nothing appears
    assert os.listdir(tmp_path) == ["model.stg"]


def test_temporary_names_keep_the_suffix_and_are_recognised(tmp_path):
    tmp = temporary_path(tmp_path / "cache.npz")
    assert tmp.parent == tmp_path and tmp.suffix == ".npz" and tmp.name.startswith(".cache.")
    assert TEMPORARY_PATTERN.match(tmp.name) and TEMPORARY_PATTERN.match(temporary_path("x/noext").name)
    assert temporary_path(tmp_path / "cache.npz") != tmp
    for name in ("cache.npz", ".hidden", "frame_000001.png", ".cache.tmp.npz", ".cache.0123456z.tmp.npz"):
        assert not TEMPORARY_PATTERN.match(name), name


def test_libraries_that_take_a_path_write_through_it(tmp_path):
    path = tmp_path / "points.npz"
    with atomic_output(path) as tmp:
        np.savez(tmp, xyz=np.arange(6.0))  # numpy keeps the .npz suffix it sees
    with np.load(path) as z:
        np.testing.assert_array_equal(z["xyz"], np.arange(6.0))
    assert os.listdir(tmp_path) == ["points.npz"]


def test_leftovers_of_interrupted_writes_are_removed(tmp_path):
    keep = ["model.stg", ".hidden", "notes.tmp", ".model.stg.tmp"]
    for name in keep:
        (tmp_path / name).write_text("x")
    stale = [temporary_path(tmp_path / "model.stg"), temporary_path(tmp_path / "checkpoint.pt"),
             temporary_path(tmp_path / "frames_uint8.npy")]
    for path in stale:
        path.write_text("half")
    assert remove_leftovers(tmp_path, "checkpoint.pt") == 1  # only that file's
    assert not stale[1].exists() and stale[0].exists()
    assert remove_leftovers(tmp_path) == 2
    assert sorted(os.listdir(tmp_path)) == sorted(keep)
    assert remove_leftovers(tmp_path / "missing") == 0


def test_a_render_cleans_up_after_an_interrupted_one(tmp_path):
    from stg_runtime.video import FrameWriter
    frames = tmp_path / "frames"
    frames.mkdir()
    temporary_path(frames / "frame_000003.png").write_bytes(b"half a png")
    video_leftover = temporary_path(tmp_path / "orbit.mp4")
    video_leftover.write_bytes(b"half a video")
    other = temporary_path(tmp_path / "other.mp4")
    other.write_bytes(b"another render's")
    FrameWriter(frames, 30.0, 8, 8).close()
    assert os.listdir(frames) == []
    pytest.importorskip("cv2")
    FrameWriter(tmp_path / "orbit.mp4", 30.0, 8, 8).close(ok=False)
    assert not video_leftover.exists() and other.exists()  # only this video's leftovers
