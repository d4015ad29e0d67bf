"""Time evaluation on the GPU (numba.cuda): stg_runtime.timeeval.evaluate's formulas, one thread per
Gaussian, on a segment uploaded once (DeviceSegment).

Unlike timeeval.evaluate nothing is compacted: all N Gaussians are returned, those whose temporal
opacity is below 1/255 with that opacity, which the splatter's opacity floor then culls (the same
decision, and the same (depth, index) order among the rest).
"""
from __future__ import annotations

import math

import numpy as np
from numba import cuda

from .cuda_launch import launch
from .model import Segment
from .timeeval import time_channels


@cuda.jit
def _evaluate(tau, opacity, t_center, t_scale, position, rotation, scale, features, time_channels,
              means, quats, scales, opacities, feats):
    i = cuda.grid(1)
    if i >= opacity.shape[0]:
        return
    d = tau - t_center[i]
    opacities[i] = opacity[i] * math.exp(-t_scale[i] * d * d)
    n_pos = position.shape[1]
    n_rot = rotation.shape[1]
    for a in range(3):  # Horner: b_0 + d (b_1 + d (b_2 + ...))
        acc = position[i, n_pos - 1, a]
        for k in range(n_pos - 2, -1, -1):
            acc = acc * d + position[i, k, a]
        means[i, a] = acc
    norm = np.float32(0.0)
    for a in range(4):
        acc = rotation[i, n_rot - 1, a]
        for k in range(n_rot - 2, -1, -1):
            acc = acc * d + rotation[i, k, a]
        quats[i, a] = acc
        norm += acc * acc
    norm = math.sqrt(norm)
    if norm > np.float32(0.0):
        for a in range(4):
            quats[i, a] /= norm
    else:  # a zero quaternion has no rotation: the identity
        quats[i, 0] = np.float32(1.0)
    for a in range(3):
        scales[i, a] = scale[i, a]
    channels = features.shape[1]
    first_time = channels - time_channels
    for c in range(first_time):
        feats[i, c] = features[i, c]
    for c in range(first_time, channels):
        feats[i, c] = d * features[i, c]


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
