"""Synchronisation of the cameras from their pictures: integer frame offsets.

Each camera's clip is summed up by two signals over its frames (SignalMeter), computed on a small grey
thumbnail: its motion energy (the mean absolute change from the previous frame) and the change of its
mean brightness. Cameras that film the same moving scene see these rise and fall together; the frame
lag of one camera behind another is where the Pearson correlation of their signals, over the frames
both have, peaks (pair_lag). The lags of all pairs are joined along a maximum spanning tree of their
confidences (the most certain pairs first, so a camera that sees little of another's view is reached
through its neighbours).

Offsets: camera c's offset o_c is the frame of its clip that shows the moment the prepared video starts;
frame o_c + k of every camera shows the same moment (the smallest offset is 0). A camera that started
recording d frames after another has an offset d smaller.

Confidence: the peak correlation minus the best correlation at least 2 frames away from the peak, in
[0, 2]; below LOW_CONFIDENCE the peak is hardly distinct (a static or periodic scene, cameras that see
different motion) and the report warns.
"""
from __future__ import annotations

from typing import NamedTuple, Sequence

import numpy as np

#: Thumbnail (width, height) the signals are computed on.
THUMBNAIL = (64, 48)
#: An offset found with a confidence below this is named in a warning.
LOW_CONFIDENCE = 0.1


class SignalMeter:
    """The signals of one clip, fed one frame at a time (add); `signal` returns them, (F, 2)."""

    def __init__(self):
        self._prev = None
        self._rows: list[tuple[float, float]] = []

    def add(self, rgb: np.ndarray) -> None:
        """Add the next frame, (H, W, 3) uint8 RGB."""
        import cv2

        grey = cv2.resize(cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY), THUMBNAIL,
                          interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0
        motion = 0.0 if self._prev is None else float(np.abs(grey - self._prev).mean())
        self._rows.append((motion, float(grey.mean())))
        self._prev = grey

    def signal(self) -> np.ndarray:
        """(F, 2) float64: per frame the motion energy and the change of mean brightness from the previous
        frame (frame 0 repeats frame 1's values), in grey levels of [0, 1]."""
        rows = np.array(self._rows, np.float64).reshape(-1, 2)
        if len(rows) > 1:
            rows[1:, 1] = np.diff(rows[:, 1])
            rows[0] = rows[1]
        return rows


class Offset(NamedTuple):
    """A camera's offset (frames, module docstring) and its confidence (None: given, not estimated)."""

    frames: int
    confidence: float | None


def _standardised(signal: np.ndarray) -> np.ndarray:
    """Each channel of signal (F, K) to zero mean and unit variance; a flat channel (no motion, no
    change of brightness) becomes zeros."""
    centred = signal - signal.mean(0)
    std = centred.std(0)
    return np.where(std > 1e-6, centred / np.maximum(std, 1e-12), 0.0)


def correlation(a: np.ndarray, b: np.ndarray, lag: int) -> float:
    """Pearson correlation of a[t + lag] with b[t] (a, b: (F, K) signals) over the t both have, all
    channels together; 0 where nothing varies."""
    start, stop = max(0, -lag), min(len(b), len(a) - lag)
    x, y = a[start + lag:stop + lag], b[start:stop]
    x, y = x - x.mean(0), y - y.mean(0)
    norm = np.sqrt((x * x).sum() * (y * y).sum())
    return float((x * y).sum() / norm) if norm > 1e-12 else 0.0


def pair_lag(a: np.ndarray, b: np.ndarray, max_lag: int) -> tuple[int, float]:
    """(lag, confidence): b's frame t shows what a's frame t + lag shows, for the lag in
    [-max_lag, max_lag] of the highest correlation (the smallest lag of equal ones: 0 where nothing
    varies); confidence as in the module docstring."""
    a, b = _standardised(a), _standardised(b)
    lags = np.array(sorted(range(-max_lag, max_lag + 1), key=lambda d: (abs(d), d)))
    scores = np.array([correlation(a, b, int(d)) for d in lags])
    best = int(np.argmax(scores))
    others = scores[np.abs(lags - lags[best]) >= 2]
    second = float(others.max()) if len(others) else -1.0
    return int(lags[best]), max(0.0, float(scores[best]) - max(second, -1.0))


def estimate_offsets(signals: Sequence[np.ndarray], max_offset: int) -> list[Offset]:
    """The offsets (module docstring) of cameras with per-frame signals (F_c, 2) (SignalMeter.signal),
    searching lags up to max_offset frames either way. Each camera's confidence is that of the pair
    that placed it in the spanning tree (the first camera's: its most confident pair)."""
    n = len(signals)
    lag = np.zeros((n, n), np.int64)
    conf = np.full((n, n), -1.0)
    for i in range(n):
        for j in range(i + 1, n):
            d, c = pair_lag(signals[i], signals[j], max_offset)
            lag[i, j], lag[j, i], conf[i, j], conf[j, i] = d, -d, c, c
    # start of each camera's clip, in frames after camera 0's (a camera d frames late starts at +d)
    start = {0: 0}
    confidence = {0: float(conf[0].max()) if n > 1 else 1.0}
    while len(start) < n:
        i, j = max(((i, j) for i in start for j in range(n) if j not in start), key=lambda ij: conf[ij])
        start[j] = start[i] + int(lag[i, j])
        confidence[j] = float(conf[i, j])
    latest = max(start.values())
    return [Offset(latest - start[c], confidence[c]) for c in range(n)]
