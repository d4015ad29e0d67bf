"""Format 1.3 segments: context frames and crossfades (formats/stg-v1.md, "Segments and crossfades"):
Segment.retimed keeps every render, Model.segments_at gives the spec's weights, the reader and writer
keep the keys (and write 1.3 only when they are used), bad values are refused, and the Player's image
inside a crossfade is the weighted sum of the two segments' own renders."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from stg_runtime import format as stg_format
from stg_runtime.demo import demo_model
from stg_runtime.format import FormatError
from stg_runtime.model import Model
from stg_runtime.player import Player

FPS = 30.0


@pytest.fixture(scope="module")
def demo():
    return demo_model("full", fps=FPS, num_frames=60)


def crossfaded(demo, fade: int = 4, context: int = 2) -> Model:
    """Two 30-frame segments, the first half of the demo and the second half of another demo scene
    (other colours and decoder), each with `context` frames of context across the seam at frame 30,
    crossfaded over `fade` frames."""
    other = demo_model("full", fps=FPS, num_frames=60, seed=1).segments[0]
    first = replace(demo.segments[0].retimed(0, 30), context_frames=(0, context))
    second = replace(other.retimed(30, 30), context_frames=(context, 0), crossfade_frames=fade)
    return Model("full", FPS, [first, second], cameras=demo.cameras)


def test_retimed_segment_renders_the_same(demo):
    seg = demo.segments[0]
    part = seg.retimed(10, 30)
    assert (part.start_frame, part.num_frames, part.context_frames) == (10, 30, (10, 20))
    whole, cut = Player(demo, device="cpu"), Player(Model("full", FPS, [part], cameras=demo.cameras), device="cpu")
    cam = demo.cameras[0]
    for frame in (10, 24, 39):
        np.testing.assert_allclose(cut.render_frame(cam, frame), whole.render_frame(cam, frame), atol=1e-4)
    # retimed back, the attributes come back (up to float32 rounding)
    back = part.retimed(0, 60)
    for name, values in seg.arrays().items():
        np.testing.assert_allclose(getattr(back, name), values, rtol=1e-5, atol=1e-5, err_msg=name)
    assert back.context_frames == (0, 0)


def test_segments_at_follows_the_spec(demo):
    model = crossfaded(demo, fade=4)
    first, second = model.segments
    weights = {}
    for frame in range(26, 34):
        parts = model.segments_at(frame / FPS)
        weights[frame] = [(s is second, round(w, 6)) for s, _, w in parts]
        for seg, tau, _ in parts:
            assert tau == pytest.approx((frame - seg.start_frame) / seg.num_frames)
    assert weights[27] == [(False, 1.0)] and weights[32] == [(True, 1.0)]
    assert weights[28] == [(False, 0.875), (True, 0.125)]
    assert weights[29] == [(False, 0.625), (True, 0.375)]
    assert weights[30] == [(False, 0.375), (True, 0.625)]
    assert weights[31] == [(False, 0.125), (True, 0.875)]
    # b = 0 and b = 1: hard cuts at the boundary
    for fade in (0, 1):
        hard = crossfaded(demo, fade=fade)
        assert [len(hard.segments_at(f / FPS)) for f in range(26, 34)] == [1] * 8
        assert hard.segments_at(29 / FPS)[0][0] is hard.segments[0] and hard.segments_at(30 / FPS)[0][0] is hard.segments[1]


def test_player_blends_the_two_segments_renders(demo):
    model = crossfaded(demo, fade=4)
    player = Player(model, device="cpu")
    cam = demo.cameras[0]
    alone = [Player(Model("full", FPS, [replace(s, crossfade_frames=0)], cameras=demo.cameras), device="cpu")
             for s in model.segments]
    # each segment alone, rendered beyond its own frames (at its tau outside [0, 1])
    a = alone[0]._render(model.segments[0], (29 - 0) / 30, cam, "host")
    b = alone[1]._render(model.segments[1], (29 - 30) / 30, cam, "host")
    got = player.render_all(cam, 29 / FPS)
    for name, x, y, z in zip(("rgb", "features", "alpha", "depth"), a, b, got):
        np.testing.assert_allclose(z, 0.625 * x + 0.375 * y, atol=1e-6, err_msg=name)
    assert np.abs(a.rgb - b.rgb).max() > 0.05  # the two halves differ there: the blend is visible
    # outside the crossfade: one segment, as before
    np.testing.assert_array_equal(player.render_frame(cam, 27), alone[0].render_frame(cam, 27))


def test_file_round_trip_and_versions(demo):
    model = crossfaded(demo, fade=4, context=3)
    data = stg_format.dumps(model)
    assert data[8:12] == bytes([1, 0, 3, 0])  # version 1.3
    back = stg_format.loads(data)
    assert [(s.context_frames, s.crossfade_frames) for s in back.segments] == [((0, 3), 0), ((3, 0), 4)]
    plain = Model("full", FPS, [replace(s, context_frames=(0, 0), crossfade_frames=0) for s in model.segments],
                  cameras=demo.cameras)
    assert stg_format.dumps(plain)[8:12] == bytes([1, 0, 0, 0])  # nothing of 1.3 used: 1.0, as before


def test_model_refuses_bad_crossfades(demo):
    seg = demo.segments[0]
    first, second = seg.retimed(0, 30), seg.retimed(30, 30)
    with pytest.raises(ValueError, match="segment 0 has crossfade_frames"):
        Model("full", FPS, [replace(first, crossfade_frames=2), second])
    with pytest.raises(ValueError, match="too short for its crossfades"):
        Model("full", FPS, [first, replace(second, crossfade_frames=61)])
    short = [seg.retimed(0, 4), replace(seg.retimed(4, 4), crossfade_frames=4), replace(seg.retimed(8, 4), crossfade_frames=6)]
    with pytest.raises(ValueError, match="segment 1 .4 frames. is too short for its crossfades .4 in, 6 out."):
        Model("full", FPS, short)
    with pytest.raises(ValueError, match="context_frames must be two counts"):
        replace(first, context_frames=(-1, 0))


@pytest.mark.parametrize("entry, message", [
    ({"context_frames": [1]}, "context_frames must be a list of two integers"),
    ({"context_frames": [1, -2]}, "context_frames must be a list of two integers"),
    ({"context_frames": [True, 0]}, "context_frames must be a list of two integers"),
    ({"crossfade_frames": 2.5}, "crossfade_frames must be an integer"),
    ({"crossfade_frames": 2 ** 25}, "crossfade_frames must be an integer"),
])
def test_reader_refuses_bad_keys(demo, entry, message):
    import hashlib
    import json
    data = stg_format.dumps(crossfaded(demo))
    _, major, minor, length = stg_format.PREFIX.unpack_from(data)
    header = json.loads(data[stg_format.PREFIX.size:stg_format.PREFIX.size + length])
    header["segments"][1].update(entry)
    text = json.dumps(header).encode()
    text += b" " * (-(stg_format.PREFIX.size + len(text)) % 8)
    body = stg_format.PREFIX.pack(stg_format.MAGIC, major, minor, len(text)) + text \
        + data[stg_format.PREFIX.size + length:-32]
    with pytest.raises(FormatError, match=message):
        stg_format.loads(body + hashlib.sha256(body).digest())
