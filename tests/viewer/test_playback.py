"""The time slider's clock (stg_runtime.viewer.playback)."""
from pathlib import Path

import pytest

from stg_runtime import Player
from stg_runtime.viewer.playback import Playback

VECTORS = Path(__file__).resolve().parents[2] / "formats" / "vectors"


def test_range_is_the_models_frames_across_segments():
    player = Player(VECTORS / "lite.stg", device="cpu")  # two segments
    assert len(player.model.segments) == 2
    p = Playback.of(player)
    assert (p.first, p.last) == pytest.approx((player.frame_times()[0], player.frame_times()[-1]))
    boundary = player.model.segments[1].start_frame / player.fps
    assert p.first < boundary < p.last  # playback crosses the boundary
    p.playing = True
    p.seek(boundary - 0.5 / player.fps)
    t = p.advance(1.0 / player.fps)
    assert player.model.segment_at(t)[0] is player.model.segments[1]


def test_pause_loop_speed_and_seek():
    p = Playback(0.0, 0.9, fps=10)
    assert p.advance(0.5) == 0.0  # paused
    p.playing = True
    assert p.advance(0.25) == pytest.approx(0.25)
    p.speed = 2.0
    assert p.advance(0.1) == pytest.approx(0.45)
    assert p.frame == 4
    p.seek(0.85)
    p.speed = 1.0
    assert p.advance(0.15) == pytest.approx(0.0, abs=1e-6)  # 0.9 is the last frame, then frame 0 again
    p.loop = False
    p.seek(0.8)
    assert p.advance(0.5) == pytest.approx(0.9) and not p.playing
    assert p.seek(-3) == 0.0 and p.seek(7) == 0.9


def test_tick_advances_by_wall_clock_time():
    p = Playback(0.0, 0.9, fps=10)
    p.playing = True
    assert p.tick(now=100.0) == 0.0  # the first tick starts the clock
    assert p.tick(now=100.3) == pytest.approx(0.3)
    assert p.tick(now=100.35) == pytest.approx(0.35)
    p.playing = False
    assert p.tick(now=105.0) == pytest.approx(0.35)
    p.playing = True
    assert p.tick(now=105.1) == pytest.approx(0.45)  # the pause is not counted


def test_loop_wraps_when_advanced_in_steps_shorter_than_a_frame():
    # the viewer's clock and every browser's stream tick it, often far more often than the frame rate
    p = Playback(0.0, 0.9, fps=10)
    p.playing = True
    p.seek(0.85)
    times = [p.advance(0.01) for _ in range(30)]
    assert max(times) == pytest.approx(0.9)  # the last frame is shown ...
    assert sum(t == pytest.approx(0.9) for t in times) == 10  # ... for 1 / fps = 0.1 s, in 0.01 s steps
    assert times[-1] == pytest.approx(0.15, abs=1e-6) and p.playing  # then frame 0 again, still playing
