"""The clock behind the viewer's time slider: play, pause, loop and speed over a model's frames.

Times are seconds of the video, as `Player.render` takes them; the range is the model's first to last
frame, so playback runs across segment boundaries (the Player picks the segment for each time).
"""
from __future__ import annotations

import threading
import time

import numpy as np


class Playback:
    """Current time `time` in [first, last] seconds (frame k of the model at k / fps). `advance(dt)`
    moves it by dt * speed while playing: past `last` it stops there and pauses when `loop` is off;
    with `loop` on, the last frame is shown for 1 / fps like the others and then the time wraps to
    `first`, however small the steps it is advanced by. Thread-safe."""

    def __init__(self, first: float, last: float, fps: float):
        if not last >= first:
            raise ValueError(f"playback range [{first}, {last}] s is empty")
        self.first, self.last, self.fps = float(first), float(last), float(fps)
        self._position = self.first  # the time, or beyond `last` while the last frame is shown
        self.playing = False
        self.loop = True
        self.speed = 1.0
        self._lock = threading.Lock()
        self._last_tick: float | None = None

    @classmethod
    def of(cls, player) -> "Playback":
        """The playback range of a Player: its first to its last frame."""
        times = player.frame_times()
        return cls(float(times[0]), float(times[-1]), player.fps)

    @property
    def time(self) -> float:
        """The current time in seconds, in [first, last]."""
        return min(self._position, self.last)

    @property
    def frame(self) -> int:
        """The index (from the video's frame 0) of the frame shown at the current time."""
        return int(np.floor(self.time * self.fps + 1e-6))

    def seek(self, t: float) -> float:
        """Set the time (clamped to the range); returns it."""
        with self._lock:
            self._position = min(max(float(t), self.first), self.last)
            return self._position

    def tick(self, now: float | None = None) -> float:
        """Advance by the wall-clock seconds since the last tick (time.monotonic(), or `now`); returns
        the time. Whoever needs the current time calls it: the slider's clock and every browser's
        stream, so a stream that renders faster than the slider moves still gets a new time per frame."""
        now = time.monotonic() if now is None else now
        with self._lock:
            last, self._last_tick = self._last_tick, now
        return self.advance(0.0 if last is None else max(now - last, 0.0))

    def advance(self, seconds: float) -> float:
        """Move on by `seconds` of wall-clock time (times speed) while playing; returns the time."""
        with self._lock:
            if not self.playing:
                return self.time
            t = self._position + seconds * self.speed
            span = self.last - self.first
            if t > self.last and not (self.loop and span > 0):
                t, self.playing = self.last, False
            elif t >= self.last + 1.0 / self.fps - 1e-9:  # the last frame has been shown for 1 / fps
                t = self.first + (t - self.first + 1e-9) % (span + 1.0 / self.fps)
            self._position = t
            return self.time
