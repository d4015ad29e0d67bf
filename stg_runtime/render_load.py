"""How much work a frame is for a splatter: the rendering load of a model seen by a camera at a time.

    render_load(means, quats, scales, opacities, camera) -> RenderLoad
    scene_load(model, camera, t) -> RenderLoad        (time evaluation first, as Player.render does)

A RenderLoad holds, under the rules of formats/stg-v1.md section 3 (the same float32 decisions as
stg_runtime.splat_cpu, whose projection, depth order and tile lists it reuses):

- `layers` (H, W) int32: per pixel, how many Gaussians were composited (added a weight w > 0) before
  the pixel stopped (its transmittance would have fallen below T_STOP) or the list ended;
- `footprints` (in_view,) int32: per Gaussian in view, the pixels it reaches with alpha >= 1/255
  inside its 3-sigma footprint, clipped to the image, whatever lies in front of it;
- `in_view`: the Gaussians that reach at least one pixel so;
- `tile_entries`: entries of the 16x16 tile lists (what binning writes and compositing walks).

It describes a scene, not a machine: benchmarks print it beside their frame rates so that two figures
can be compared only when their scenes load a splatter alike.
"""
from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from .camera import Camera
from .projection import camera_params
from .splat_cpu import _PACKED, _aligned_empty, _blend, _project, bin_tiles, sort_by_depth
from .timeeval import evaluate

_TILE = 16


@dataclass(frozen=True)
class RenderLoad:
    """The load statistics of one frame (see the module docstring)."""

    layers: np.ndarray
    footprints: np.ndarray
    in_view: int
    total: int
    tile_entries: int

    @property
    def mean_layers(self) -> float:
        """Gaussians composited per pixel, mean over the image."""
        return float(self.layers.mean()) if self.layers.size else 0.0

    @property
    def p99_layers(self) -> float:
        """Gaussians composited per pixel, 99th percentile over the image."""
        return float(np.percentile(self.layers, 99)) if self.layers.size else 0.0

    @property
    def mean_footprint(self) -> float:
        """Mean footprint area of the Gaussians in view, pixels."""
        return float(self.footprints.mean()) if self.footprints.size else 0.0

    def as_dict(self) -> dict:
        """The statistics as plain numbers (for JSON)."""
        return {"gaussians": self.total, "in_view": self.in_view, "mean_layers": self.mean_layers,
                "p99_layers": self.p99_layers, "mean_footprint_px": self.mean_footprint,
                "tile_entries": self.tile_entries}

    def summary(self) -> str:
        """One line: layers per pixel (mean, p99), mean footprint, Gaussians in view."""
        return (f"layers/pixel {self.mean_layers:.1f} (p99 {self.p99_layers:.0f}), footprint "
                f"{self.mean_footprint:.0f} px, {self.in_view}/{self.total} Gaussians in view")


@numba.njit(parallel=True, cache=True, fastmath={"contract"})
def _count_layers(packed, tile_start, tile_ids, tiles_x, width, height, layers):
    """layers[y, x] = the Gaussians composited at pixel (x, y), tile by tile, with the compositor's
    per-pixel rules (splat_cpu._blend)."""
    half = np.float32(0.5)
    for tile in numba.prange(tile_start.shape[0] - 1):
        x0 = (tile % tiles_x) * _TILE
        y0 = (tile // tiles_x) * _TILE
        x1 = min(x0 + _TILE, width) - 1
        y1 = min(y0 + _TILE, height) - 1
        T = np.ones((_TILE, _TILE), np.float32)
        live = (x1 - x0 + 1) * (y1 - y0 + 1)
        for k in range(tile_start[tile], tile_start[tile + 1]):
            g = tile_ids[k]
            u0, u1 = np.int64(packed[g, 8]), np.int64(packed[g, 9])
            v0, v1 = np.int64(packed[g, 10]), np.int64(packed[g, 11])
            left = np.float32(u0) + half
            right = np.float32(u1) + half
            bottom = np.float32(v1) + half
            for y in range(max(v0, y0), min(v1, y1) + 1):
                for x in range(max(u0, x0), min(u1, x1) + 1):
                    t = T[y - y0, x - x0]
                    if t < 0:
                        continue
                    w, t, stop = _blend(np.float32(x) + half, np.float32(y) + half, t, packed[g, 0], packed[g, 1],
                                        packed[g, 2], packed[g, 3], packed[g, 4], packed[g, 5], left, right, bottom)
                    T[y - y0, x - x0] = t
                    layers[y, x] += w > 0
                    live -= stop
            if live == 0:
                break


@numba.njit(parallel=True, cache=True, fastmath={"contract"})
def _footprints(packed, ids, out):
    """out[j] = the pixels of Gaussian ids[j]'s rectangle where it reaches alpha >= 1/255 on a fresh
    pixel (splat_cpu._blend with transmittance 1)."""
    half = np.float32(0.5)
    one = np.float32(1.0)
    for j in numba.prange(ids.shape[0]):
        g = ids[j]
        u0, u1 = np.int64(packed[g, 8]), np.int64(packed[g, 9])
        v0, v1 = np.int64(packed[g, 10]), np.int64(packed[g, 11])
        left = np.float32(u0) + half
        right = np.float32(u1) + half
        bottom = np.float32(v1) + half
        n = 0
        for y in range(v0, v1 + 1):
            for x in range(u0, u1 + 1):
                w, t, stop = _blend(np.float32(x) + half, np.float32(y) + half, one, packed[g, 0], packed[g, 1],
                                    packed[g, 2], packed[g, 3], packed[g, 4], packed[g, 5], left, right, bottom)
                n += w > 0
        out[j] = n


def render_load(means, quats, scales, opacities, camera: Camera) -> RenderLoad:
    """The RenderLoad of M Gaussians (means (M, 3), quats (M, 4) wxyz, scales (M, 3), opacities (M,),
    as for splat_cpu.rasterize) seen by `camera`."""
    f32 = lambda x, shape: np.ascontiguousarray(np.asarray(x, np.float32).reshape(shape))  # noqa: E731
    means = f32(means, (-1, 3))
    m = means.shape[0]
    quats, scales, opacities = f32(quats, (m, 4)), f32(scales, (m, 3)), f32(opacities, (m,))
    W, H = camera.width, camera.height
    packed = _aligned_empty((m, _PACKED))
    tiles = np.empty((m, 4), np.int32)
    depth = np.empty(m, np.float64)
    _project(means, quats, scales, opacities, np.zeros((m, 1), np.float32), camera_params(camera), W, H, _TILE,
             packed, tiles, depth)
    order = sort_by_depth(tiles, depth)
    tiles_x, tiles_y = -(-W // _TILE), -(-H // _TILE)
    tile_start, tile_ids, _ = bin_tiles(order, tiles, tiles_x, tiles_y)
    layers = np.zeros((H, W), np.int32)
    _count_layers(packed, tile_start, tile_ids, tiles_x, W, H, layers)
    footprints = np.empty(order.shape[0], np.int32)
    _footprints(packed, order, footprints)
    footprints = footprints[footprints > 0]
    return RenderLoad(layers, footprints, int(footprints.shape[0]), m, int(tile_start[-1]))


def scene_load(model, camera: Camera, t: float) -> RenderLoad:
    """The RenderLoad of `model` (a stg_runtime Model) at time t (seconds, as Player.render takes it)."""
    segment, tau = model.segment_at(t)
    g = evaluate(segment, tau)
    return render_load(g.means, g.quats, g.scales, g.opacities, camera)
