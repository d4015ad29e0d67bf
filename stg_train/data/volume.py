"""Initial points sampled in the training cameras' common view volume, at photo-consistent depths
(numpy only), between the cameras' near/far depth bounds (stg_train.data.bounds): the whole images
(--init volume), or only the pixels that SfM points leave uncovered (--init combined,
stg_train.data.points).
"""
from __future__ import annotations

import numpy as np

from stg_runtime.camera import Camera

from .visibility import pixel_hits, samplable_pixels


def _unproject(camera: Camera, u: np.ndarray, v: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """World points (..., 3) at camera-space depth `depth` through pixel centres (u + 0.5, v + 0.5)."""
    return camera.unproject(u + 0.5, v + 0.5, depth)


def _project(camera: Camera, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixel columns, rows (integer, the pixel hit) and a bool mask of the points the camera sees inside
    its image (stg_train.data.visibility.pixel_hits)."""
    return pixel_hits(camera, xyz)


def _box3(image: np.ndarray) -> np.ndarray:
    """3x3 box blur of an (H, W, 3) image (edges replicated), against noise in colour matching."""
    pad = np.pad(image, ((1, 1), (1, 1), (0, 0)), mode="edge")
    h, w = image.shape[:2]
    return sum(pad[dy:dy + h, dx:dx + w] for dy in range(3) for dx in range(3)) / 9.0


def sample_view_volume(dataset, num_points: int, rng: np.random.Generator, min_views: float = 0.5,
                       depth_candidates: int = 0, mask: np.ndarray | None = None):
    """Initial points sampled in the view volume of the training cameras (--init volume).

    Each point picks a training camera, a pixel and a depth in [near, far] of that camera
    (dataset.bounds), and takes the pixel's colour in frame j of that camera, where j spreads the points
    evenly over the frames (temporal centre j / num_frames, like the reference's per-frame SfM points).
    Points seen by fewer than `min_views` of the training cameras are drawn again. The depth is uniform
    when depth_candidates is 0; otherwise it is the most photo-consistent of `depth_candidates` depths
    (uniform in 1/depth, jittered): the one whose projections into the other training cameras' frame j
    have the colours closest to the source pixel's (a per-pixel plane sweep; 3x3-blurred frames).
    mask: (T, H, W) bool over the T training cameras (dataset.train_cameras order): only its pixels
    are drawn (a camera in proportion to its count of them); None: every pixel. A fisheye camera's
    pixels whose rays lie more than visibility.MAX_SAMPLE_ANGLE_DEG off its axis are never drawn (they
    have no point at a positive depth, or one far beside the rig).
    Returns xyz (N, 3) float64, rgb (N, 3) float32 in [0, 1], t_center (N,) float32.
    """
    cams = [dataset.cameras[i] for i in dataset.train_cameras]
    if dataset.bounds is None:
        raise ValueError("sample_view_volume: the dataset has no near/far bounds")
    bounds = np.asarray(dataset.bounds, dtype=np.float64)[dataset.train_cameras]
    pixels = weights = None
    if mask is not None:
        mask = np.asarray(mask, bool)
        if mask.shape != (len(cams), dataset.height, dataset.width):
            raise ValueError(f"sample_view_volume: mask of shape {mask.shape}, expected "
                             f"{(len(cams), dataset.height, dataset.width)}")
    if any(cam.model != "pinhole" for cam in cams):
        samplable = np.stack([samplable_pixels(cam) for cam in cams])
        mask = samplable if mask is None else mask & samplable
    if mask is not None:
        pixels = [np.flatnonzero(m) for m in mask]
        counts = np.array([len(p) for p in pixels], np.float64)
        if counts.sum() == 0:
            raise ValueError("sample_view_volume: the mask selects no pixel")
        weights = counts / counts.sum()
    frames = np.arange(num_points) % dataset.num_frames
    rng.shuffle(frames)
    xyz = np.zeros((num_points, 3))
    src = np.zeros(num_points, np.int64)
    u, v = np.zeros(num_points, np.int64), np.zeros(num_points, np.int64)
    todo = np.arange(num_points)
    for _ in range(50):  # after 50 draws a point stays as drawn (a rig without a common view)
        if todo.size == 0:
            break
        k = todo.size
        if pixels is None:
            src[todo] = rng.integers(0, len(cams), k)
            u[todo], v[todo] = rng.integers(0, dataset.width, k), rng.integers(0, dataset.height, k)
        else:
            src[todo] = rng.choice(len(cams), k, p=weights)
            for c in np.unique(src[todo]):
                m = todo[src[todo] == c]
                flat = pixels[c][rng.integers(0, len(pixels[c]), len(m))]
                v[m], u[m] = np.divmod(flat, dataset.width)
        depth = rng.uniform(bounds[src[todo], 0], bounds[src[todo], 1])
        for c in np.unique(src[todo]):
            m = todo[src[todo] == c]
            xyz[m] = _unproject(cams[c], u[m], v[m], depth[src[todo] == c])
        seen = sum(_project(cam, xyz[todo])[2].astype(int) for cam in cams)
        todo = todo[seen < min_views * len(cams)]
    rgb = np.zeros((num_points, 3), np.float32)
    for j in range(dataset.num_frames):
        in_frame = np.flatnonzero(frames == j)
        if in_frame.size == 0:
            continue
        images = [dataset.image(i, j) for i in dataset.train_cameras]
        rgb[in_frame] = np.stack([images[c][v[i], u[i]] for c, i in zip(src[in_frame], in_frame)])
        if depth_candidates:
            blurred = [_box3(im) for im in images]
            for c in np.unique(src[in_frame]):
                m = in_frame[src[in_frame] == c]
                xyz[m] = _photo_consistent(cams, blurred, c, u[m], v[m], bounds[c], depth_candidates, rng)
    return xyz, rgb, (frames / dataset.num_frames).astype(np.float32)


def _photo_consistent(cams, images, c, u, v, near_far, candidates, rng) -> np.ndarray:
    """(P, 3) points along the rays of pixels (u, v) of camera c at the candidate depth whose colours in
    the other cameras' images best match camera c's (mean L1 over the views that see the point)."""
    inv = np.linspace(1.0 / near_far[0], 1.0 / near_far[1], candidates)
    step = abs(inv[1] - inv[0]) if candidates > 1 else 0.0
    pts = _unproject(cams[c], u[:, None], v[:, None], 1.0 / inv[None, :])  # (P, D, 3)
    ref = images[c][v, u][:, None, :]
    cost = np.zeros(pts.shape[:2])
    count = np.zeros(pts.shape[:2])
    for k, cam in enumerate(cams):
        if k == c:
            continue
        pu, pv, ok = _project(cam, pts)
        cost += np.where(ok, np.abs(images[k][pv, pu] - ref).sum(-1), 0.0)
        count += ok
    cost = np.where(count > 0, cost / np.maximum(count, 1), np.inf)
    best = inv[np.argmin(cost, axis=1)] + rng.uniform(-0.5, 0.5, len(u)) * step
    best = np.clip(best, min(inv[0], inv[-1]), max(inv[0], inv[-1]))
    return _unproject(cams[c], u, v, 1.0 / best)
