"""Time evaluation on the GPU (numba.cuda): stg_runtime.timeeval's formulas, one thread per
Gaussian, on a segment uploaded once (DeviceSegment).

Unlike timeeval.evaluate nothing is compacted: all N Gaussians are returned, those whose temporal
opacity is below 1/255 with that opacity, which the splatter's opacity floor then culls (the same
decision, and the same (depth, index) order among the rest).
"""
from __future__ import annotations

import numpy as np
from numba import cuda

from ..model import Segment, time_channels
from ..timeeval import gaussian_at, opacity_at
from .launch import launch


_opacity_at = cuda.jit(device=True, inline=True)(opacity_at)
_gaussian_at = cuda.jit(device=True, inline=True)(gaussian_at)


@cuda.jit
def _evaluate(tau, opacity, t_center, t_scale, position, rotation, scale, features, time_channels,
              means, quats, scales, opacities, feats):
    """Thread i: Gaussian i at normalised time tau (timeeval.opacity_at and gaussian_at)."""
    i = cuda.grid(1)
    if i < opacity.shape[0]:
        opacities[i] = _opacity_at(tau, opacity, t_center, t_scale, i)
        _gaussian_at(tau, t_center, position, rotation, scale, features, time_channels, i,
                     means, quats, scales, feats, i)


class DeviceSegment:
    """A segment's parameters on the device (uploaded once) and buffers for its Gaussians at one time."""

    def __init__(self, segment: Segment):
        up = lambda a: cuda.to_device(np.ascontiguousarray(a, dtype=np.float32))  # noqa: E731
        self.opacity, self.t_center, self.t_scale = up(segment.opacity), up(segment.t_center), up(segment.t_scale)
        self.position, self.rotation = up(segment.position), up(segment.rotation)
        self.scale, self.features = up(segment.scale), up(segment.features)
        self.time_channels = time_channels(segment)
        n, c = segment.count, segment.channels
        self.means = cuda.device_array((n, 3), np.float32)
        self.quats = cuda.device_array((n, 4), np.float32)
        self.scales = cuda.device_array((n, 3), np.float32)
        self.opacities = cuda.device_array(n, np.float32)
        self.feats = cuda.device_array((n, c), np.float32)

    def evaluate(self, tau: float):
        """The Gaussians at normalised time tau, as device arrays (means (N, 3), quats (N, 4) unit wxyz,
        scales (N, 3), opacities (N,), features (N, C)), float32. They are overwritten by the next call."""
        n = self.opacity.shape[0]
        if n:
            launch(_evaluate, max(1, -(-n // 256)), 256,
                   np.float32(tau), self.opacity, self.t_center, self.t_scale, self.position, self.rotation,
                   self.scale, self.features, self.time_channels, self.means, self.quats, self.scales,
                   self.opacities, self.feats)
        return self.means, self.quats, self.scales, self.opacities, self.feats
