"""A lens's radial brightness falloff (vignetting), `1 + k1 s + k2 s^2` with s the squared distance from
the principal point over its value at the farthest image corner (appearance.radial): the polynomial
once, for the falloff the cameras learn (stg_train.rig.appearance) and the one given as known
(TrainConfig.lens_falloff, `stg-train --lens-falloff`), s over a picture's pixels (`radial_grid`), a
picture's brightness against the canonical scene's (`picture_brightness`), and the range a known one
must keep. Imports nothing at load (numpy only inside the functions that make arrays), so the command
line checks a falloff before torch loads."""
from __future__ import annotations

import math


def lens_brightness(s, k):
    """The brightness 1 + k1 s + k2 s^2 at radial values s (a float, numpy array or tensor, any shape),
    k = (k1, k2) (floats or a differentiable (2,) tensor)."""
    return 1.0 + k[0] * s + k[1] * s * s


def corner_r2(camera) -> float:
    """The squared distance, in pixels, from the camera's principal point to its farthest image corner:
    the value at which s = r^2 / corner_r2 reaches 1 (a stg_runtime Camera, or anything with cx, cy,
    width and height)."""
    return max((x - camera.cx) ** 2 + (y - camera.cy) ** 2 for x in (0, camera.width) for y in (0, camera.height))


def radial_grid(camera, shape: tuple[int, int] | None = None):
    """(h, w) float64 numpy array of s = r^2 / corner_r2 at the pixel centres (+0.5) of the camera's
    picture resized to `shape` (h, w; default: the camera's own size), r measured in the camera's pixels."""
    import numpy as np

    h, w = (camera.height, camera.width) if shape is None else shape
    u = (np.arange(w) + 0.5) * (camera.width / w) - camera.cx
    v = (np.arange(h) + 0.5) * (camera.height / h) - camera.cy
    return (u[None, :] ** 2 + v[:, None] ** 2) / corner_r2(camera)


def picture_brightness(camera, falloff=None, gains=None):
    """(H, W, 3) float32 numpy array: how bright a camera's picture is against the canonical scene's, per
    pixel and channel: its lens falloff 1 + k1 s + k2 s^2 (falloff (k1, k2); None: none) times its colour
    gains ((3,); None: 1). A picture divided by it is the scene as the canonical model renders it."""
    import numpy as np

    s = radial_grid(camera)
    brightness = np.ones_like(s) if falloff is None else lens_brightness(s, falloff)
    out = np.repeat(brightness[..., None], 3, axis=-1)
    return (out if gains is None else out * np.asarray(gains, np.float64)).astype(np.float32)


def known_falloff(k) -> tuple[float, float]:
    """(k1, k2) of a known falloff given as (k1,) or (k1, k2); ValueError unless both are finite and the
    brightness stays within (0, 2] over the image (s in [0, 1]; checked at 101 points)."""
    values = [float(v) for v in k]
    if not 1 <= len(values) <= 2 or not all(math.isfinite(v) for v in values):
        raise ValueError(f"a lens falloff is K1 or K1,K2 (finite numbers), got {tuple(k)!r}")
    k1, k2 = (values + [0.0])[:2]
    brightness = [lens_brightness(i / 100, (k1, k2)) for i in range(101)]
    if min(brightness) <= 0 or max(brightness) > 2:
        raise ValueError(f"the brightness 1 + K1 s + K2 s^2 must stay within (0, 2] for s in [0, 1]; "
                         f"K1, K2 = {k1:g}, {k2:g} give {min(brightness):.3g} .. {max(brightness):.3g}")
    return k1, k2
