"""Photometric pose alignment: the small rigid correction of one camera's pose under which a model's
renders best match that camera's pictures, the model held fixed (test-time pose optimisation, as BARF
and NeRF-- score the views of a pose-refining method).

Why: pictures fix a model only up to a similarity of the world (stg_train.rig.gauge), and a model trained
on slightly wrong poses is also slightly bent against the truth, so a view posed in another frame (the
truth's, or a calibration's) lands a fraction of a pixel off the model's own picture of that place.
Aligned, a view is scored on what the model shows rather than on where it sits.

The correction D (4x4, camera coordinates, the convention of stg_train.rig.gauge and pose_refine) is the
rotation exp([w]x) (axis-angle w, radians) followed by the shift t (world units): the aligned camera is
D W. Each Gauss-Newton step solves for (w, t / depth) from the renders' Jacobian, taken by central
differences of renders (any renderer serves: no gradient with respect to the camera is needed), the
shift counted in units of the scene's depth so that both move the picture alike. With `colour` each
step first fits the one affine colour map (3x3 + bias) from the renders to the pictures, so that a
camera whose colour differs from the model's is aligned on its geometry; the pose is the only thing
returned.
"""
from __future__ import annotations

from typing import Callable, NamedTuple, Sequence

import numpy as np

from stg_runtime.camera import Camera

from ..metrics import affine_moments
from .capture import corrected

#: Central-difference step of the parameters, in pixels that it moves the picture by (the step in
#: radians, and in units of the scene's depth, is this over the focal length): a secant over half a pixel
#: sees through a render's small steps (a ray-traced edge that flips a pixel) where a tangent would not.
STEP_PIXELS = 0.25
#: Levenberg-Marquardt damping, relative to the normal equations' diagonal.
DAMPING = 1e-3
#: A view of a video is aligned on this many of its frames (spread over them), in this many steps.
ALIGN_FRAMES, ALIGN_STEPS = 4, 3


class PoseAlignment(NamedTuple):
    """The aligned camera; its correction's rotation (degrees) and shift (world units); the mean
    squared error per colour value of the renders against the pictures before and after (after the
    affine colour map when aligned with `colour`)."""

    camera: Camera
    rotation_deg: float
    shift: float
    mse_before: float
    mse_after: float


def align_pose(render: Callable[[Camera, int], np.ndarray], camera: Camera,
               pictures: Sequence[tuple[int, np.ndarray]], depth: float, iterations: int = 3,
               colour: bool = True) -> PoseAlignment:
    """Align `camera` to its `pictures` ((frame, (H, W, 3) float image in [0, 1]) pairs; a few frames
    spread over the video suffice) against render(camera, frame) -> (H, W, 3) float image of the held
    model. depth: the scene's depth from the camera in world units (data.bounds.typical_depth), which
    scales the shift's parameter. Runs `iterations` Gauss-Newton steps (13 renders a picture each) and
    returns the best pose seen (the starting one when no step lowers the error)."""
    if not pictures:
        raise ValueError("align_pose: no picture to align to")
    if not depth > 0:
        raise ValueError(f"align_pose: the scene's depth must be positive, got {depth}")
    targets = [(frame, np.asarray(picture, np.float64).reshape(-1, 3)) for frame, picture in pictures]
    x, best_x, best_mse, first = np.zeros(6), np.zeros(6), np.inf, None
    for step in range(iterations + 1):
        renders = [_render(render, camera, x, depth, frame) for frame, _ in targets]
        colour_map = _affine(renders, targets) if colour else None
        mse = _mse(renders, targets, colour_map)
        first = mse if first is None else first
        if mse >= best_mse:  # a step that does not help ends it
            break
        best_x, best_mse = x, mse
        if step < iterations:
            x = x + _gauss_newton_step(render, camera, x, depth, targets, renders, colour_map)
    x, mse = best_x, best_mse
    return PoseAlignment(_moved(camera, x, depth), float(np.degrees(np.linalg.norm(x[:3]))),
                         float(np.linalg.norm(x[3:]) * depth), float(first), float(mse))


def align_view(render: Callable[[Camera, int], np.ndarray], camera: Camera, picture: Callable[[int], np.ndarray],
               frames: Sequence[int], depth: float, count: int = ALIGN_FRAMES,
               iterations: int = ALIGN_STEPS) -> PoseAlignment:
    """`camera` aligned (align_pose) to its pictures at `count` of `frames` spread evenly over them (all
    of them when fewer): picture(j) -> (H, W, 3) float image in [0, 1] of frame j, render(camera, j) the
    held model's render of it."""
    frames = list(frames)
    chosen = sorted({frames[k] for k in np.linspace(0, len(frames) - 1, min(count, len(frames))).round().astype(int)})
    return align_pose(render, camera, [(int(j), picture(int(j))) for j in chosen], depth, iterations=iterations)


def renders_at_most(frames: int, iterations: int = ALIGN_STEPS) -> int:
    """How many renders align_pose makes at most for `frames` pictures (a progress bar's total)."""
    return frames * (iterations + 1) + frames * 12 * iterations


def _moved(camera: Camera, x: np.ndarray, depth: float) -> Camera:
    return corrected(camera, x[:3], x[3:] * depth)


def _render(render, camera: Camera, x: np.ndarray, depth: float, frame: int) -> np.ndarray:
    """(H W, 3) float64 render of the camera corrected by x."""
    return np.asarray(render(_moved(camera, x, depth), frame), np.float64).reshape(-1, 3)


def _affine(renders: list, targets: list) -> np.ndarray:
    """(4, 3) affine colour map A, (rgb, 1) @ A ~ picture, least squares over every picture's pixels (the
    fit of the colour-aligned PSNR, metrics.affine_moments)."""
    moments = [affine_moments(r, t) for r, (_, t) in zip(renders, targets)]
    zz, zy = sum(m[0] for m in moments), sum(m[1] for m in moments)
    return np.linalg.lstsq(zz + 1e-9 * np.eye(4), zy, rcond=None)[0]


def _mapped(image: np.ndarray, colour_map: np.ndarray | None) -> np.ndarray:
    return image if colour_map is None else image @ colour_map[:3] + colour_map[3]


def _mse(renders: list, targets: list, colour_map) -> float:
    sse = sum(float(((_mapped(r, colour_map) - t) ** 2).sum()) for r, (_, t) in zip(renders, targets))
    return sse / sum(t.size for _, t in targets)


def _gauss_newton_step(render, camera, x, depth, targets, renders, colour_map) -> np.ndarray:
    """The damped Gauss-Newton update (6,) of x, the Jacobian by central differences (STEP_PIXELS)."""
    jtj, jtr = np.zeros((6, 6)), np.zeros(6)
    step = STEP_PIXELS / max(camera.fx, camera.fy)
    linear = np.eye(3) if colour_map is None else colour_map[:3]
    for (frame, target), base in zip(targets, renders):
        residual = (_mapped(base, colour_map) - target).reshape(-1)
        columns = []
        for k in range(6):
            d = np.zeros(6)
            d[k] = step
            change = _render(render, camera, x + d, depth, frame) - _render(render, camera, x - d, depth, frame)
            columns.append((change @ linear).reshape(-1) / (2 * step))
        jacobian = np.stack(columns, 1)
        jtj += jacobian.T @ jacobian
        jtr += jacobian.T @ residual
    return -np.linalg.solve(jtj + DAMPING * np.diag(np.diag(jtj)) + 1e-12 * np.eye(6), jtr)
