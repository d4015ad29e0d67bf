"""Time evaluation of Spacetime Gaussians on the CPU (paper Eq. 7-10; formats/stg-v1.md, section 2).

The float64 oracle is stg_runtime.spec.evaluate_oracle; the GPU kernel is stg_runtime.cuda.timeeval.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numba
import numpy as np

from .model import Segment, time_channels
from .spec import MIN_ALPHA


class GaussiansAt(NamedTuple):
    """Static 3D Gaussians at one instant. index: (M,) int64 rows of the segment they came from;
    means (M, 3); quats (M, 4) unit wxyz; scales (M, 3); opacities (M,); features (M, C). float32."""

    index: np.ndarray
    means: np.ndarray
    quats: np.ndarray
    scales: np.ndarray
    opacities: np.ndarray
    features: np.ndarray


def opacity_at(tau, opacity, t_center, t_scale, i):
    """Gaussian i's temporal opacity at normalised time tau (Eq. 7), float32 in, float32 out."""
    d = tau - t_center[i]
    return opacity[i] * math.exp(-t_scale[i] * d * d)


def gaussian_at(tau, t_center, position, rotation, scale, features, time_channels, i,
                means, quats, scales, feats, j):
    """Row j of means, quats (unit wxyz; a zero quaternion gives the identity), scales and feats: segment
    Gaussian i at normalised time tau (Eq. 8-10: polynomials in tau - t_center by Horner's rule; the last
    time_channels features times tau - t_center).

    opacity_at and gaussian_at are plain Python that numba compiles for each target: the CPU's
    _evaluate here, and stg_runtime.cuda.timeeval's kernel (so they call no helper functions)."""
    d = tau - t_center[i]
    n_pos = position.shape[1]
    n_rot = rotation.shape[1]
    for a in range(3):  # Horner: b_0 + d (b_1 + d (b_2 + ...))
        acc = position[i, n_pos - 1, a]
        for k in range(n_pos - 2, -1, -1):
            acc = acc * d + position[i, k, a]
        means[j, a] = acc
    norm = 0.0
    for a in range(4):
        acc = rotation[i, n_rot - 1, a]
        for k in range(n_rot - 2, -1, -1):
            acc = acc * d + rotation[i, k, a]
        quats[j, a] = acc
        norm += acc * acc
    norm = math.sqrt(norm)
    if norm > 0.0:
        for a in range(4):
            quats[j, a] /= norm
    else:
        quats[j, 0] = 1.0
    for a in range(3):
        scales[j, a] = scale[i, a]
    channels = features.shape[1]
    for c in range(channels - time_channels):
        feats[j, c] = features[i, c]
    for c in range(channels - time_channels, channels):
        feats[j, c] = d * features[i, c]


_opacity_at = numba.njit(inline="always")(opacity_at)
_gaussian_at = numba.njit(inline="always")(gaussian_at)


@numba.njit(cache=True)
def _temporal_opacity(opacity, t_center, t_scale, tau, out):
    for i in range(opacity.shape[0]):
        out[i] = _opacity_at(tau, opacity, t_center, t_scale, i)


@numba.njit(parallel=True, cache=True)
def _evaluate(index, tau, t_center, position, rotation, scale, features, time_channels,
              means, quats, scales, feats):
    for j in numba.prange(index.shape[0]):
        _gaussian_at(tau, t_center, position, rotation, scale, features, time_channels, index[j],
                     means, quats, scales, feats, j)


def evaluate(segment: Segment, tau: float, min_opacity: float = MIN_ALPHA) -> GaussiansAt:
    """The segment's Gaussians at normalised time tau, keeping those with opacity(tau) >= min_opacity."""
    opac = np.empty(segment.count, dtype=np.float32)
    _temporal_opacity(segment.opacity, segment.t_center, segment.t_scale, np.float32(tau), opac)
    index = np.flatnonzero(opac >= min_opacity)
    m, c = index.shape[0], segment.channels
    means = np.empty((m, 3), np.float32)
    quats = np.empty((m, 4), np.float32)
    scales = np.empty((m, 3), np.float32)
    feats = np.empty((m, c), np.float32)
    _evaluate(index, np.float32(tau), segment.t_center, segment.position, segment.rotation, segment.scale,
              segment.features, time_channels(segment), means, quats, scales, feats)
    return GaussiansAt(index, means, quats, scales, opac[index], feats)
