"""Image quality metrics for evaluation (numpy; SSIM through scikit-image), as the paper's Sec. 6.1
defines them, and the held-out evaluation of a model through the runtime Player.

Images are float arrays (H, W, 3) with values in [0, 1]. The training loss has its own differentiable
SSIM (stg_train.losses); these are the reported figures.

Dynamic and static regions: for a static camera, `dynamic_mask` marks the pixels whose ground truth
changes over the clip; PSNR and SSIM are then also reported over those pixels ("dynamic_psnr",
"dynamic_ssim") and over the others ("static_psnr", "static_ssim"), so that moving content is judged
apart from the background that dominates the whole-image figures.

Colour-aligned PSNR ("aligned_psnr"): for captures whose cameras disagree in exposure and colour, the
literature also scores each held-out camera after one affine colour map (3x3 + bias) per camera, fitted
by least squares from the renders to the ground truth over all of that camera's evaluated frames. It is
computed exactly from per-image second moments (`affine_moments`), so no image is kept; the mapped
image is not clipped to [0, 1].

Seams of a model cut into segments (`evaluate_seams`): each frame's PSNR, and the temporal error of
consecutive frames, mean |(R[j+1] - R[j]) - (G[j+1] - G[j])| (`temporal_errors`: a rendered change that
the ground truth does not have, such as a pop where two segments meet), summarised by `seam_figures`
as the worst dip of a segment's first or last frame below the interior frames and the flicker ratio
of the worst seam against the pairs inside segments.
"""
from __future__ import annotations

import time

import numpy as np

#: The figures of a held-out evaluation kept in metrics.json and printed by the command lines (and the
#: LPIPS_KEYS where LPIPS was computed).
HELDOUT_KEYS = ("psnr", "aligned_psnr", "ssim", "dssim1", "dssim2", "fps", "images", "cameras")
#: The per-region figures of a held-out evaluation (dynamic_mask): means over the images, and the
#: fraction of the held-out pixels that are dynamic and the threshold that decided it.
REGION_KEYS = ("dynamic_psnr", "dynamic_ssim", "static_psnr", "static_ssim", "dynamic_fraction",
               "dynamic_threshold")
#: dynamic_mask's default threshold: a change of more than 0.1 (25.5 of 255 levels) in some colour
#: channel over the clip makes a pixel dynamic (docs/dynamic.md says why this value).
DYNAMIC_THRESHOLD = 0.1
#: scikit-image's SSIM averages its local map over the pixels at least this far from the border (half
#: of its 7x7 window).
SSIM_BORDER = 3
#: LPIPS's networks as the paper's evaluation uses them (AlexNet; its code also reports VGG).
LPIPS_NETS = ("alex", "vgg")
LPIPS_KEYS = tuple(f"lpips_{net}" for net in LPIPS_NETS)


def psnr_of_mse(mse: float) -> float:
    """PSNR in dB of a mean squared error of values in [0, 1] (peak 1); inf for mse 0."""
    return float("inf") if mse <= 0 else float(-10.0 * np.log10(mse))


def psnr(image: np.ndarray, reference: np.ndarray) -> float:
    """Peak signal-to-noise ratio in dB for images in [0, 1] (peak 1); inf for identical images."""
    return psnr_of_mse(float(np.mean((np.asarray(image, np.float64) - np.asarray(reference, np.float64)) ** 2)))


def affine_moments(image: np.ndarray, reference: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, int]:
    """Sufficient statistics of an affine colour fit from `image` to `reference` (H, W, 3): with z = (rgb,
    1) per pixel of the image and y the reference's rgb, (sum z z^T (4, 4), sum z y^T (4, 3), sum |y|^2,
    number of pixels), float64."""
    x = np.asarray(image, dtype=np.float64).reshape(-1, 3)
    y = np.asarray(reference, dtype=np.float64).reshape(-1, 3)
    z = np.concatenate([x, np.ones((len(x), 1))], axis=1)
    return z.T @ z, z.T @ y, float(np.sum(y * y)), len(x)


def aligned_psnrs(moments: list) -> list[float]:
    """PSNR (dB) of each image after the one affine colour map (3x3 + bias) that fits all of them best
    (least squares over their pixels together); `moments`: affine_moments of each image of one camera."""
    zz = sum(m[0] for m in moments)
    zy = sum(m[1] for m in moments)
    fit = np.linalg.lstsq(zz + 1e-9 * np.eye(4), zy, rcond=None)[0]  # (4, 3): y ~ z @ fit
    out = []
    for m_zz, m_zy, yy, n in moments:
        sse = float(np.trace(fit.T @ m_zz @ fit) - 2 * np.trace(fit.T @ m_zy) + yy)
        out.append(psnr_of_mse(max(sse / (3 * n), 1e-12)))
    return out


def ssim(image: np.ndarray, reference: np.ndarray, data_range: float = 1.0) -> float:
    """scikit-image's structural_similarity over the colour channels (its default 7x7 uniform window)."""
    from skimage.metrics import structural_similarity

    return float(structural_similarity(np.asarray(image, np.float64), np.asarray(reference, np.float64),
                                       channel_axis=-1, data_range=data_range))


def dssim1(image: np.ndarray, reference: np.ndarray) -> float:
    """(1 - SSIM) / 2 with data_range = 1 (the paper's DSSIM_1)."""
    return (1.0 - ssim(image, reference, 1.0)) / 2.0


def dssim2(image: np.ndarray, reference: np.ndarray) -> float:
    """(1 - SSIM) / 2 with data_range = 2 (the paper's DSSIM_2)."""
    return (1.0 - ssim(image, reference, 2.0)) / 2.0


def ssim_map(image: np.ndarray, reference: np.ndarray, data_range: float = 1.0) -> np.ndarray:
    """(H, W, 3) local SSIM of scikit-image's structural_similarity (7x7 uniform window, per colour
    channel); `ssim` is its mean over the pixels at least SSIM_BORDER from the image border."""
    from skimage.metrics import structural_similarity

    _, full = structural_similarity(np.asarray(image, np.float64), np.asarray(reference, np.float64),
                                    channel_axis=-1, data_range=data_range, full=True)
    return full


def dynamic_mask(frames, threshold: float = DYNAMIC_THRESHOLD) -> np.ndarray:
    """(H, W) bool: the pixels of a static camera whose ground truth changes over the clip.

    frames: iterable of the camera's (H, W, 3) ground-truth images in [0, 1] (float) over the clip (the
    frames evaluated). A pixel is dynamic when, in some colour channel, its largest and smallest value
    over the frames differ by more than `threshold` (same units: 0.1 is 25.5 of 255 levels):
    max_c (max_t I[t, c] - min_t I[t, c]) > threshold. Moving and spinning objects, what appears or
    vanishes and the shadows they cast are dynamic; the rest of the picture is static. No labels are
    needed, but the camera must not move, and noise in the frames (lossy video) above the threshold
    would count as motion: lossless frames (the default for the N3V layout with PNG frames) are best.
    """
    low = high = None
    for image in frames:
        image = np.asarray(image, np.float32)
        low = image.copy() if low is None else np.minimum(low, image)
        high = image.copy() if high is None else np.maximum(high, image)
    if low is None:
        raise ValueError("dynamic_mask: no frames")
    return (high - low).max(axis=-1) > threshold


def region_metrics(image: np.ndarray, reference: np.ndarray, mask: np.ndarray,
                   ssim_values: np.ndarray | None = None) -> dict[str, float | None]:
    """{"psnr", "ssim"} of `image` against `reference` over the pixels where the (H, W) bool `mask` is
    True: PSNR (dB, peak 1) of their mean squared error, and the mean of the local SSIM map (ssim_map,
    data_range 1; pass it as ssim_values when already computed) over those of them at least SSIM_BORDER
    from the border. A figure is None when no pixel is left to average."""
    mask = np.asarray(mask, bool)
    diff = np.asarray(image, np.float64)[mask] - np.asarray(reference, np.float64)[mask]
    s = ssim_map(image, reference) if ssim_values is None else ssim_values
    b = SSIM_BORDER
    inner = np.zeros_like(mask)
    inner[b:mask.shape[0] - b, b:mask.shape[1] - b] = mask[b:mask.shape[0] - b, b:mask.shape[1] - b]
    return {"psnr": psnr_of_mse(float(np.mean(diff ** 2))) if diff.size else None,
            "ssim": float(s[inner].mean()) if inner.any() else None}


def lpips_models(nets=LPIPS_NETS) -> tuple[dict, str | None]:
    """({net: network}, None) of the lpips package's LPIPS (version 0.1) for each of `nets`, or ({}, why
    not). The package is optional (python -m pip install lpips, the `lpips` extra, which needs a
    torchvision that imports beside torch), and its backbones' weights download on first use."""
    try:
        import lpips
    except Exception as e:  # noqa: BLE001 - ImportError, or a torchvision that does not fit torch
        return {}, f"LPIPS not computed: the lpips package cannot be imported ({type(e).__name__}: {e})"
    models = {}
    for net in nets:
        try:
            models[net] = lpips.LPIPS(net=net, version="0.1", verbose=False).eval()
        except Exception as e:  # noqa: BLE001 - offline: the backbone's weights cannot be downloaded
            return {}, f"LPIPS not computed: its {net} network cannot be loaded ({type(e).__name__}: {e})"
    return models, None


def lpips_distance(network, image: np.ndarray, reference: np.ndarray) -> float:
    """LPIPS of two (H, W, 3) images in [0, 1]: both mapped to [-1, 1] (the networks' input range) as
    (1, 3, H, W) float32 tensors; the network's distance averaged over the image."""
    import torch

    def tensor(x):
        return torch.from_numpy(np.ascontiguousarray(x, np.float32)).permute(2, 0, 1)[None] * 2.0 - 1.0

    with torch.no_grad():
        return float(network(tensor(image), tensor(reference)).mean())


def image_metrics(image: np.ndarray, reference: np.ndarray, lpips: dict | None = None,
                  dynamic: np.ndarray | None = None) -> dict[str, float | None]:
    """All per-image figures: psnr (dB), ssim (data_range 1), dssim1, dssim2, lpips_<net> for each
    network of `lpips` (lpips_models' dict), and with an (H, W) bool `dynamic` mask (dynamic_mask) the
    region_metrics of its pixels and of the others: dynamic_psnr, dynamic_ssim, static_psnr, static_ssim
    (None for an empty region)."""
    s1, s2 = ssim(image, reference, 1.0), ssim(image, reference, 2.0)
    figures = {"psnr": psnr(image, reference), "ssim": s1, "dssim1": (1 - s1) / 2, "dssim2": (1 - s2) / 2}
    if dynamic is not None:
        local = ssim_map(image, reference)
        for region, mask in (("dynamic", dynamic), ("static", ~np.asarray(dynamic, bool))):
            for key, value in region_metrics(image, reference, mask, local).items():
                figures[f"{region}_{key}"] = value
    for net, network in (lpips or {}).items():
        figures[f"lpips_{net}"] = lpips_distance(network, image, reference)
    return figures


def summarise(rows: list[dict], masks: list[np.ndarray], threshold: float) -> dict:
    """The means over the images of per-image figures `rows` (image_metrics): every figure they share,
    the region ones over the images where they are not None (None where none has them), plus
    "dynamic_fraction" (the share of dynamic pixels over the cameras' (H, W) `masks`) and
    "dynamic_threshold"."""
    means = {}
    for key in rows[0]:
        if key in ("camera", "frame"):
            continue
        values = [r[key] for r in rows if r.get(key) is not None]
        means[key] = float(np.mean(values)) if values else None
    means["dynamic_fraction"] = float(np.mean([m.mean() for m in masks])) if masks else None
    means["dynamic_threshold"] = float(threshold)
    return means


def evaluate_images(render, dataset, camera_indices=None, frames=None, lpips: dict | None = None,
                    threshold: float = DYNAMIC_THRESHOLD) -> dict:
    """Compare `render(camera_index, frame)` ((H, W, 3) in [0, 1]) with the ground truth for dataset
    cameras (default: the held-out ones) at every frame (or `frames`), with each camera's dynamic_mask
    over those frames at `threshold`.

    Returns summarise's means ("psnr", "aligned_psnr" (the module docstring), "ssim", "dssim1",
    "dssim2", the REGION_KEYS, "lpips_<net>" for each network of `lpips`), "seconds" (spent in
    `render`), "images", "cameras" (names), "per_frame" (the per-image figures with camera name and
    frame, and "temporal_error": temporal_errors of the pair ending at that frame, None where the
    camera's previous image is not the frame before)."""
    cams = dataset.test_cameras if camera_indices is None else list(camera_indices)
    frames = list(range(dataset.num_frames)) if frames is None else list(frames)
    if not cams or not frames:
        raise ValueError("no camera or no frame to evaluate")
    rows, masks, seconds = [], [], 0.0
    for ci in cams:
        mask = dynamic_mask((dataset.image(ci, j) for j in frames), threshold)
        masks.append(mask)
        moments, first, previous = [], len(rows), None
        for j in frames:
            start = time.perf_counter()
            image = render(ci, j)
            seconds += time.perf_counter() - start
            reference = dataset.image(ci, j)
            moments.append(affine_moments(image, reference))
            pair = None if previous is None or previous[0] != j - 1 else float(
                temporal_errors([previous[1], image], [previous[2], reference])[0])
            rows.append({"camera": dataset.cameras[ci].name, "frame": j,
                         **image_metrics(image, reference, lpips, mask), "temporal_error": pair})
            previous = (j, image, reference)
        for row, value in zip(rows[first:], aligned_psnrs(moments)):
            row["aligned_psnr"] = value
    return {**summarise(rows, masks, threshold), "seconds": seconds, "images": len(rows),
            "cameras": [dataset.cameras[ci].name for ci in cams], "per_frame": rows}


def evaluate_player(player, dataset, camera_indices=None, frames=None, lpips: dict | None = None,
                    threshold: float = DYNAMIC_THRESHOLD) -> dict:
    """Render dataset cameras (default: the held-out ones) at every frame (or `frames`) through a
    stg_runtime Player and compare with the ground truth (evaluate_images, dynamic regions at
    `threshold`).

    Returns {"psnr", "ssim", "dssim1", "dssim2"}, the REGION_KEYS (and "lpips_<net>" for each network of
    `lpips`): means over the images; "fps" (images rendered per second of Player.render time, after one
    warm-up render), "images", "cameras" (names), "per_frame" (list of per-image figures with camera
    name and frame)."""
    cams = dataset.test_cameras if camera_indices is None else list(camera_indices)
    start_frame = getattr(dataset, "start_frame", 0)  # a Dataset.frame_range view: its frame j is video frame start + j
    if not cams:
        raise ValueError("evaluate_player: no camera or no frame to evaluate")
    player.render(dataset.cameras[cams[0]], player.start_time)  # warm-up (numba, onnxruntime)
    try:
        result = evaluate_images(lambda ci, j: player.render(dataset.cameras[ci], (start_frame + j) / dataset.fps),
                                 dataset, cams, frames, lpips, threshold)
    except ValueError as e:
        raise ValueError(f"evaluate_player: {e}") from None
    seconds = result.pop("seconds")
    return {**result, "fps": result["images"] / seconds if seconds > 0 else float("inf")}


def heldout(result: dict) -> dict:
    """The HELDOUT_KEYS, REGION_KEYS (and LPIPS_KEYS where computed) of an evaluate_player result."""
    return {k: result[k] for k in HELDOUT_KEYS + REGION_KEYS + LPIPS_KEYS if k in result}


def temporal_errors(renders, truths) -> np.ndarray:
    """(F - 1,) float64: for each pair of consecutive frames j, j + 1, the mean over pixels and channels
    of |(R[j+1] - R[j]) - (G[j+1] - G[j])|: how far the rendered change departs from the true change
    (a pop where two independent models meet shows as a large value). renders, truths: F images
    (H, W, 3) in [0, 1] of one view."""
    r = np.asarray(renders, np.float64)
    g = np.asarray(truths, np.float64)
    if r.shape != g.shape or r.ndim != 4 or len(r) < 2:
        raise ValueError(f"temporal_errors: need two equal (F >= 2, H, W, 3) stacks, got {r.shape} and {g.shape}")
    return np.abs(np.diff(r, axis=0) - np.diff(g, axis=0)).mean(axis=(1, 2, 3))


def seam_figures(frame_psnrs, pair_errors, starts) -> dict:
    """The seams of a model cut into segments starting at frames `starts` (the first is 0), from
    per-frame PSNRs (F,) (dB; e.g. means over views) and temporal_errors (F - 1,) (means over views).
    Boundary frames are each segment's first and last frames; the others are interior. Returns
    interior_psnr (mean over interior frames), boundary {frame: psnr}, worst_dip (interior_psnr minus
    the lowest boundary PSNR, dB; positive = worse), interior_pair_error (mean temporal error of the
    pairs within a segment), seams {first frame of a segment: temporal error of the pair across its
    seam} and flicker_ratio (the largest seam error over interior_pair_error; None for one segment)."""
    psnrs = np.asarray(frame_psnrs, np.float64)
    pairs = np.asarray(pair_errors, np.float64)
    frames = len(psnrs)
    starts = sorted(set(int(s) for s in starts))
    if not starts or starts[0] != 0 or starts[-1] >= frames or len(pairs) != frames - 1:
        raise ValueError(f"seam_figures: segment starts {starts} do not cut {frames} frames, "
                         f"or {len(pairs)} pair errors for {frames} frames")
    ends = starts[1:] + [frames]
    boundary = sorted({s for s in starts} | {e - 1 for e in ends})
    interior = np.setdiff1d(np.arange(frames), boundary)
    interior_psnr = float(psnrs[interior].mean()) if len(interior) else float("nan")
    seams = {s: float(pairs[s - 1]) for s in starts[1:]}
    inner = np.setdiff1d(np.arange(frames - 1), [s - 1 for s in starts[1:]])
    inner_error = float(pairs[inner].mean()) if len(inner) else float("nan")
    return {"interior_psnr": interior_psnr, "boundary": {f: float(psnrs[f]) for f in boundary},
            "worst_dip": interior_psnr - float(psnrs[boundary].min()),
            "interior_pair_error": inner_error, "seams": seams,
            "flicker_ratio": max(seams.values()) / inner_error if seams and inner_error > 0 else None}


def evaluate_seams(result: dict, segment_starts, require_seam: bool = True) -> dict | None:
    """seam_figures of an evaluate_images / evaluate_player `result` over consecutive frames, for a model
    whose segments start at `segment_starts` (frames numbered as the rows' "frame"): each frame's PSNR
    and temporal error are the means over the result's cameras (its "per_frame" rows). None unless the
    rows cover consecutive frames holding a seam (two segments or more), or, with require_seam False,
    two consecutive frames or more (one segment: its first and last frames against its interior)."""
    rows = result["per_frame"]
    frames = sorted({r["frame"] for r in rows})
    if len(frames) < 2 or frames != list(range(frames[0], frames[-1] + 1)):
        return None
    starts = [s - frames[0] for s in segment_starts if frames[0] < s <= frames[-1]]
    if not starts and require_seam:
        return None
    by_frame = {j: [r for r in rows if r["frame"] == j] for j in frames}
    psnrs = [np.mean([r["psnr"] for r in by_frame[j]]) for j in frames]
    pairs = [np.mean([r["temporal_error"] for r in by_frame[j]]) for j in frames[1:]]
    figures = seam_figures(psnrs, pairs, [0] + starts)
    shift = lambda d: {frames[0] + k: v for k, v in d.items()}  # noqa: E731  (back to video frames)
    return {**figures, "boundary": shift(figures["boundary"]), "seams": shift(figures["seams"])}
