"""Initial motion from optical flow: the velocity of each initial point, triangulated from the 2D optical
flow between its frame and the next in the training cameras that see it (scene flow).

Gaussians start with zero motion in the reference implementation, and within a short run temporal
opacity learns to fake what moves faster than the motion coefficients can grow (docs/dynamic.md). A
point on a moving surface at frame j moves by a world displacement D to frame j + 1; in every camera c
that sees it, its pixel moves by J_c D, J_c the (2, 3) Jacobian of c's projection at the point, and that
pixel motion is what the optical flow of c's frames j -> j + 1 measures there. With two or more such
cameras, D is the least-squares solution of J_c D = flow_c; the velocity is D x num_frames (world
units per unit of normalised time, the motion's linear coefficient, stg_train.params).

    initial_velocity(dataset, xyz, rgb, t_center) -> (N, 3) velocity

A camera counts for a point when the point projects into its image and the frame's colour there is
within `colour_tol` of the point's own (so that an occluded point does not take the occluder's flow).
Points whose flow is below `min_flow` pixels in every camera used stay at rest, as do points with fewer
than two cameras: flow noise on static content would otherwise set everything adrift.
"""
from __future__ import annotations

from typing import Callable

import cv2
import numpy as np

from stg_runtime.camera import Camera

from .visibility import pixel_hits

#: Step (world units) of the central differences of the projection's Jacobian, relative to depth.
_JACOBIAN_STEP = 1e-4
#: The flow is computed on images resized to a shorter side in [FLOW_MIN_SIDE, FLOW_MAX_SIDE] pixels.
#: Smaller ones are enlarged: DIS's 8-pixel patches and its smoothing otherwise average small moving
#: objects with their background (at 80x60 it found a third of the moving sphere's flow; enlarged 4x,
#: within about 10 %). Larger ones are reduced, which keeps the flow of a full-size capture cheap.
FLOW_MIN_SIDE = 240
FLOW_MAX_SIDE = 540


def frame_flow(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """(H, W, 2) float32 optical flow (pixels of these images, (du, dv)) from image `first` to `second`
    ((H, W, 3) float in [0, 1]): OpenCV's DIS flow (medium preset) on the grey images, resized (cubic)
    to a shorter side within [FLOW_MIN_SIDE, FLOW_MAX_SIDE], the flow resized back and rescaled."""
    h, w = first.shape[:2]
    side = min(h, w)
    scale = min(max(side, FLOW_MIN_SIDE), FLOW_MAX_SIDE) / side
    size = (max(1, round(w * scale)), max(1, round(h * scale)))
    grey = []
    for im in (first, second):
        g = cv2.cvtColor(np.clip(im * 255 + 0.5, 0, 255).astype(np.uint8), cv2.COLOR_RGB2GRAY)
        grey.append(g if size == (w, h) else cv2.resize(g, size, interpolation=cv2.INTER_CUBIC))
    flow = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM).calc(grey[0], grey[1], None)
    if size == (w, h):
        return flow
    back = cv2.INTER_AREA if scale > 1 else cv2.INTER_LINEAR
    flow = cv2.resize(flow, (w, h), interpolation=back)
    flow[..., 0] *= w / size[0]
    flow[..., 1] *= h / size[1]
    return flow


def projection_jacobian(camera: Camera, xyz: np.ndarray) -> np.ndarray:
    """(N, 2, 3): d(pixel u, v) / d(world x, y, z) at points xyz (N, 3), by central differences (any
    camera model)."""
    xyz = np.asarray(xyz, np.float64)
    _, z = camera.project(xyz)
    h = (_JACOBIAN_STEP * np.maximum(np.abs(z), 1e-3))[:, None]
    jac = np.empty((xyz.shape[0], 2, 3))
    for k in range(3):
        step = np.zeros(3)
        step[k] = 1.0
        plus, _ = camera.project(xyz + h * step)
        minus, _ = camera.project(xyz - h * step)
        jac[:, :, k] = (plus - minus) / (2 * h)
    return jac


def triangulate_displacement(jacobians: np.ndarray, flows: np.ndarray, used: np.ndarray) -> np.ndarray:
    """(N, 3) world displacements D minimising sum_c |J_c D - flow_c|^2 over the cameras `used`.

    jacobians (C, N, 2, 3), flows (C, N, 2) pixels, used (C, N) bool. Points with fewer than two cameras
    get 0."""
    w = used[..., None, None].astype(np.float64)
    normal = np.einsum("cnki,cnkj->nij", jacobians * w, jacobians)  # sum_c J^T J
    rhs = np.einsum("cnki,cnk->ni", jacobians * w, np.where(used[..., None], flows, 0.0))
    enough = used.sum(0) >= 2
    out = np.zeros((jacobians.shape[1], 3))
    if enough.any():
        a = normal[enough] + 1e-12 * np.eye(3)
        out[enough] = np.linalg.solve(a, rhs[enough][..., None])[..., 0]
    return out


def initial_velocity(dataset, xyz: np.ndarray, rgb: np.ndarray, t_center: np.ndarray, colour_tol: float = 0.1,
                     min_flow: float = 0.5, progress: Callable[[int, int], None] | None = None) -> np.ndarray:
    """(N, 3) float32 initial velocities (world units per unit of normalised time) of points xyz (N, 3)
    with colours rgb (N, 3) in [0, 1] at frames round(t_center x num_frames); see the module docstring.
    progress(done, total): called after each frame's flows."""
    xyz = np.asarray(xyz, np.float64)
    n_frames = dataset.num_frames
    velocity = np.zeros((xyz.shape[0], 3), np.float32)
    if n_frames < 2 or xyz.shape[0] == 0:
        return velocity
    frame = np.clip(np.rint(np.asarray(t_center, np.float64) * n_frames).astype(np.int64), 0, n_frames - 1)
    cams = [dataset.cameras[i] for i in dataset.train_cameras]
    frames_used = np.unique(frame)
    for done, j in enumerate(frames_used, 1):
        points = np.flatnonzero(frame == j)
        j0 = min(j, n_frames - 2)  # the last frame takes the flow that ends there
        jac, flow, used = [], [], []
        for ci, cam in zip(dataset.train_cameras, cams):
            u, v, visible = pixel_hits(cam, xyz[points])
            same = np.abs(dataset.image(ci, j)[v, u] - rgb[points]).max(-1) <= colour_tol
            f = frame_flow(dataset.image(ci, j0), dataset.image(ci, j0 + 1))[v, u]
            jac.append(projection_jacobian(cam, xyz[points]))
            flow.append(f)
            used.append(visible & same)
        jac, flow, used = np.stack(jac), np.stack(flow).astype(np.float64), np.stack(used)
        moving = (np.linalg.norm(flow, axis=-1) * used).max(0) >= min_flow
        d = triangulate_displacement(jac, flow, used & moving[None])
        velocity[points] = (d * n_frames).astype(np.float32)
        if progress is not None:
            progress(done, len(frames_used))
    return velocity
