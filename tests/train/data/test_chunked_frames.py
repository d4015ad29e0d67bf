"""The lazily decoded frame cache (stg_train.data.frames.ChunkedFrames): the same pixels as an eager
load, from PNG frames and from videos; cut at segments, a segment's view decodes only its own chunk,
also after pickling (as sent to a worker); uncut, it is the eager load's cache file."""
from __future__ import annotations

import pickle

import numpy as np
import pytest

pytest.importorskip("cv2")

from stg_train.data import load_dataset  # noqa: E402
from stg_train.data.frames import ChunkedFrames  # noqa: E402

SCENE = dict(num_cameras=3, num_frames=8, fps=4.0, width=32, height=24)


@pytest.fixture(scope="module")
def scene_dir(synthetic_n3v):
    return synthetic_n3v("chunked_scene", **SCENE)


@pytest.mark.parametrize("from_video", [False, True])
def test_chunks_hold_the_eager_pixels(scene_dir, tmp_path, from_video):
    eager = load_dataset(scene_dir, from_video=from_video, cache_dir=tmp_path / "eager")
    lazy = load_dataset(scene_dir, from_video=from_video, cache_dir=tmp_path / "lazy", lazy=True)
    assert isinstance(lazy.frames, ChunkedFrames) and not (tmp_path / "lazy").exists()  # nothing decoded yet
    lazy = lazy.chunked([(0, 3), (3, 5)])
    for c in range(3):
        for f in range(8):
            np.testing.assert_array_equal(lazy.frame(c, f), eager.frame(c, f))
    np.testing.assert_array_equal(lazy.frames[1, 4, ::5, ::5], eager.frames[1, 4, ::5, ::5])
    cache = next((tmp_path / "lazy").iterdir())
    assert sorted(p.name for p in cache.iterdir()) == ["frames_0-2", "frames_3-7"]


def test_a_segment_view_decodes_only_its_chunk(scene_dir, tmp_path):
    dataset = load_dataset(scene_dir, cache_dir=tmp_path, lazy=True).chunked([(0, 4), (4, 4)])
    segment = pickle.loads(pickle.dumps(dataset.frame_range(4, 4)))
    assert segment.num_frames == 4 and segment.start_frame == 4
    first = segment.frame(2, 0)
    cache = next(tmp_path.iterdir())
    assert [p.name for p in cache.iterdir()] == ["frames_4-7"]
    np.testing.assert_array_equal(first, dataset.frame(2, 4))
    with pytest.raises(IndexError, match="out of range"):
        segment.frame(0, 4)
    with pytest.raises(IndexError, match="unsupported index"):
        segment.frames[0]
    with pytest.raises(ValueError, match="consecutive"):
        dataset.chunked([(0, 4), (5, 3)])


def test_uncut_it_is_the_eager_cache(scene_dir, tmp_path):
    load_dataset(scene_dir, cache_dir=tmp_path)
    (cache,) = tmp_path.iterdir()
    stamp = (cache / "frames_uint8.npy").stat().st_mtime_ns
    lazy = load_dataset(scene_dir, cache_dir=tmp_path, lazy=True)
    lazy.frame(0, 7)
    assert (cache / "frames_uint8.npy").stat().st_mtime_ns == stamp and [p.name for p in cache.iterdir()
                                                                          if p.is_dir()] == []
