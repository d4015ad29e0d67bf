"""The rig's lens falloff (vignetting) measured from its own pictures, before training
(`TrainConfig(lens_falloff="auto")`, `stg-train --lens-falloff auto`).

Why not learn it with the scene: a falloff that every lens shares is, for a rig whose cameras converge,
nearly the same thing as a darker rim of the scene, so training takes it into the scene (docs/training.md,
"Real captures"). Two cameras that see one surface point at the same instant see it at different
distances from their principal points, though, and that difference is what this module measures:

1. For each training camera c and its `neighbours` nearest training cameras c' (by centre), at a few
   frames: dense optical flow from the picture of c to that of c' (OpenCV DIS, on brightness-normalised grey
   images, downscaled to at most `max_side` pixels), kept where it is consistent forwards and
   backwards, the picture is smooth (no edge to misalign) and neither colour is clipped.
2. Every such pixel pair gives, per channel, log I_c - log I_c' = g_c - g_c' + log V(s) - log V(s'),
   with g the cameras' log colour gains (exposure and white balance), s the squared distance from the
   principal point over its value at the farthest corner (stg_train.lens), and log V(s) = a1 s + a2 s^2.
   That is linear in (g, a1, a2): iteratively reweighted least squares (Cauchy weights) with the gains'
   sum held at 0 (only gains relative to the rig's mean can be told from its pictures).
3. The pictures are corrected by the estimate and the flow is computed again (`rounds` times): the
   flow of pictures that still vignette pulls the estimate towards no falloff (docs/training.md).

The log-polynomial is then written as the trainer's `1 + k1 s + k2 s^2` (a least-squares fit over
s in [0, 1]). Pinhole and fisheye cameras alike (s is measured in pixels from the principal point).
"""
from __future__ import annotations

from typing import Callable, NamedTuple

import cv2
import numpy as np

from .lens import corner_r2, known_falloff, lens_brightness

#: Flow pairs kept only where forward and backward flow agree to this many pixels (of the scaled image).
FB_TOLERANCE = 0.3
#: and where |Laplacian| of the grey picture (in [0, 1]) is below this: smooth surfaces, no edges.
SMOOTH = 0.05
#: Colours below or above these (in [0, 1], any channel) are dark or clipped: left out.
DARK, CLIPPED = 0.05, 0.98
#: At most this many pixel pairs enter the fit (a random subset beyond).
MAX_PAIRS = 200_000
#: Fewer pixel pairs than this: the cameras do not overlap enough to measure anything.
MIN_PAIRS = 2_000


class FalloffEstimate(NamedTuple):
    """k: (k1, k2) of the brightness 1 + k1 s + k2 s^2; gains: (C, 3) each training camera's colour
    gains relative to the rig's (their geometric mean over the cameras is 1; rows in
    dataset.train_cameras order); pairs: pixel pairs found in the last round; frames: the frames used."""

    k: tuple[float, float]
    gains: np.ndarray
    pairs: int
    frames: tuple[int, ...]

    @property
    def corner_brightness(self) -> float:
        """The brightness at the farthest image corner (s = 1), 1 + k1 + k2."""
        return float(lens_brightness(1.0, self.k))


def estimate_lens_falloff(dataset, frames=None, neighbours: int = 4, rounds: int = 3, max_side: int = 320,
                          seed: int = 0, progress: Callable[[int, int], None] | None = None) -> FalloffEstimate:
    """The falloff shared by the training cameras of `dataset` (stg_train.data.Dataset), from `frames`
    (default: the first and the middle frame). progress(done, total) is called per camera pair and round.
    Raises ValueError when the cameras overlap too little (fewer than MIN_PAIRS pixel pairs) or the
    estimate leaves the range a known falloff must keep (stg_train.lens.known_falloff)."""
    cams = list(dataset.train_cameras)
    if len(cams) < 2:
        raise ValueError(f"the lens falloff needs two or more training cameras, the dataset has {len(cams)}")
    frames = tuple(sorted({0, dataset.num_frames // 2})) if frames is None else tuple(int(f) for f in frames)
    scale = min(1.0, max_side / max(dataset.width, dataset.height))
    pictures = {(c, f): _scaled(dataset.image(c, f), scale) for c in cams for f in frames}
    # the colours compared, blurred once: a sub-pixel misalignment of the flow then matters less
    blurred = {key: cv2.GaussianBlur(p, (0, 0), 1.0) for key, p in pictures.items()}
    radial = {c: _radial(dataset.cameras[c], pictures[c, frames[0]].shape[:2]) for c in cams}
    pairs = _neighbour_pairs(dataset, cams, neighbours)
    rng = np.random.default_rng(seed)
    logv, gains, total = np.zeros(2), np.zeros((len(cams), 3)), 0
    work, done = rounds * len(pairs) * len(frames), 0
    for _ in range(rounds):
        rows = []
        for f in frames:
            corrected = {c: (pictures[c, f] / _brightness(radial[c], logv, gains[i])[..., None]).astype(np.float32)
                         for i, c in enumerate(cams)}
            for i, j in pairs:
                rows.append(_pixel_pairs(blurred[cams[i], f], blurred[cams[j], f], corrected[cams[i]],
                                         corrected[cams[j]], radial[cams[i]], radial[cams[j]], i, j))
                done += 1
                if progress is not None:
                    progress(done, work)
        data = [np.concatenate(parts) for parts in zip(*rows)]
        total = len(data[0])
        if total < MIN_PAIRS:
            raise ValueError(f"the training cameras overlap too little to measure their lens falloff "
                             f"({total} pixel pairs, at least {MIN_PAIRS} needed)")
        if total > MAX_PAIRS:
            keep = rng.choice(total, MAX_PAIRS, replace=False)
            data = [d[keep] for d in data]
        gains, logv = _fit(*data, num_cameras=len(cams))
    k = _as_polynomial(logv)
    known_falloff(k)  # the trainer's range; ValueError outside it
    return FalloffEstimate(k, np.exp(gains), total, frames)


def _scaled(image: np.ndarray, scale: float) -> np.ndarray:
    """(H, W, 3) float32 picture resized by `scale` (area averaging)."""
    if scale == 1.0:
        return image.astype(np.float32)
    h, w = image.shape[:2]
    return cv2.resize(image, (max(1, round(w * scale)), max(1, round(h * scale))), interpolation=cv2.INTER_AREA)


def _radial(camera, shape) -> np.ndarray:
    """(h, w) s of each pixel centre of the camera's picture resized to `shape` (h, w)
    (stg_train.appearance.radial at full size)."""
    h, w = shape
    u = (np.arange(w) + 0.5) * (camera.width / w) - camera.cx
    v = (np.arange(h) + 0.5) * (camera.height / h) - camera.cy
    return ((u[None, :] ** 2 + v[:, None] ** 2) / corner_r2(camera)).astype(np.float32)


def _neighbour_pairs(dataset, cams: list, neighbours: int) -> list[tuple[int, int]]:
    """(i, j) positions in `cams` of each camera and its `neighbours` nearest (by centre)."""
    centres = np.array([dataset.cameras[c].center for c in cams])
    out = []
    for i in range(len(cams)):
        order = np.argsort(np.linalg.norm(centres - centres[i], axis=1), kind="stable")
        out += [(i, int(j)) for j in order[1:neighbours + 1]]
    return out


def _brightness(s: np.ndarray, logv: np.ndarray, log_gain: np.ndarray) -> np.ndarray:
    """(h, w) the falloff's brightness times the camera's mean gain (for the flow's pictures only)."""
    return np.exp(logv[0] * s + logv[1] * s * s + log_gain.mean())


def _grey(picture: np.ndarray) -> np.ndarray:
    """uint8 grey picture scaled to a mean of 0.4 (the flow compares patterns, not exposures)."""
    g = cv2.cvtColor(picture, cv2.COLOR_RGB2GRAY)
    return np.clip(g * (0.4 * 255 / max(float(g.mean()), 1e-3)), 0, 255).astype(np.uint8)


def _pixel_pairs(a, b, a_flow, b_flow, s_a, s_b, i, j):
    """Pixels of picture a (h, w, 3; blurred) matched in picture b by the flow of the corrected pictures
    a_flow, b_flow: (camera i, camera j, s at a, s at b, log colour at a (n, 3), log colour at b (n, 3))."""
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    ga, gb = _grey(a_flow), _grey(b_flow)
    fwd, bwd = dis.calc(ga, gb, None), dis.calc(gb, ga, None)
    h, w = ga.shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float32)
    u2, v2 = u + fwd[..., 0], v + fwd[..., 1]
    back = cv2.remap(bwd, u2, v2, cv2.INTER_LINEAR)
    ok = (np.hypot(fwd[..., 0] + back[..., 0], fwd[..., 1] + back[..., 1]) < FB_TOLERANCE)
    ok &= (u2 > 1) & (u2 < w - 2) & (v2 > 1) & (v2 < h - 2)
    ok &= np.abs(cv2.Laplacian(ga.astype(np.float32) / 255, cv2.CV_32F)) < SMOOTH
    ca = a[ok]
    cb = np.stack([cv2.remap(np.ascontiguousarray(b[..., k]), u2, v2, cv2.INTER_LINEAR)[ok] for k in range(3)], 1)
    good = (ca.min(1) > DARK) & (cb.min(1) > DARK) & (ca.max(1) < CLIPPED) & (cb.max(1) < CLIPPED)
    n = int(good.sum())
    return (np.full(n, i), np.full(n, j), s_a[ok][good], cv2.remap(s_b, u2, v2, cv2.INTER_LINEAR)[ok][good],
            np.log(ca[good]), np.log(cb[good]))


def _fit(ci, cj, si, sj, li, lj, num_cameras: int, iterations: int = 8, scale: float = 0.05):
    """IRLS (Cauchy weights, `scale` in log units) of li - lj = g_i - g_j + a1 (si - sj) + a2 (si^2 - sj^2)
    per channel, (a1, a2) shared by the channels and each channel's gains summing to 0: returns
    (g (C, 3), (a1, a2)). The normal equations are summed per camera pair (np.bincount), O(pairs)."""
    c = num_cameras
    d = np.stack([si - sj, si * si - sj * sj], 1)  # (n, 2)
    t = li - lj  # (n, 3)
    w = np.ones_like(t)
    x = np.zeros(3 * c + 2)
    for _ in range(iterations):
        normal, rhs = np.zeros((3 * c + 2, 3 * c + 2)), np.zeros(3 * c + 2)
        for k in range(3):
            wk, g = w[:, k], slice(k * c, (k + 1) * c)
            pair = np.bincount(ci * c + cj, wk, c * c).reshape(c, c)
            normal[g, g] = np.diag(pair.sum(1) + pair.sum(0)) - pair - pair.T + 1e4  # + the gauge, sum g = 0
            for m in range(2):
                cross = np.bincount(ci, wk * d[:, m], c) - np.bincount(cj, wk * d[:, m], c)
                normal[g, 3 * c + m] = normal[3 * c + m, g] = cross
            normal[3 * c:, 3 * c:] += (d * wk[:, None]).T @ d
            rhs[g] = np.bincount(ci, wk * t[:, k], c) - np.bincount(cj, wk * t[:, k], c)
            rhs[3 * c:] += (d * wk[:, None]).T @ t[:, k]
        x = np.linalg.solve(normal, rhs)
        gains = x[:3 * c].reshape(3, c).T
        r = t - (gains[ci] - gains[cj] + (d @ x[3 * c:])[:, None])
        w = 1.0 / (1.0 + (r / scale) ** 2)
    return x[:3 * c].reshape(3, c).T, x[3 * c:]


def _as_polynomial(logv: np.ndarray) -> tuple[float, float]:
    """(k1, k2) of 1 + k1 s + k2 s^2 closest to exp(a1 s + a2 s^2) over s in [0, 1]."""
    s = np.linspace(0.0, 1.0, 101)
    k, *_ = np.linalg.lstsq(np.stack([s, s * s], 1), np.exp(logv[0] * s + logv[1] * s * s) - 1.0, rcond=None)
    return float(k[0]), float(k[1])
