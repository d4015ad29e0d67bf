"""Image quality metrics for evaluation (numpy; SSIM through scikit-image), as the paper's Sec. 6.1
defines them, and the held-out evaluation of a model through the runtime Player.

Images are float arrays (H, W, 3) with values in [0, 1]. The training loss has its own differentiable
SSIM (stg_train.losses); these are the reported figures.
"""
from __future__ import annotations

import time

import numpy as np

#: The figures of a held-out evaluation kept in metrics.json and printed by the command lines (and the
#: LPIPS_KEYS where LPIPS was computed).
HELDOUT_KEYS = ("psnr", "ssim", "dssim1", "dssim2", "fps", "images", "cameras")
#: LPIPS's networks as the paper's evaluation uses them (AlexNet; its code also reports VGG).
LPIPS_NETS = ("alex", "vgg")
LPIPS_KEYS = tuple(f"lpips_{net}" for net in LPIPS_NETS)


def psnr_of_mse(mse: float) -> float:
    """PSNR in dB of a mean squared error of values in [0, 1] (peak 1); inf for mse 0."""
    return float("inf") if mse <= 0 else float(-10.0 * np.log10(mse))


def psnr(image: np.ndarray, reference: np.ndarray) -> float:
    """Peak signal-to-noise ratio in dB for images in [0, 1] (peak 1); inf for identical images."""
    return psnr_of_mse(float(np.mean((np.asarray(image, np.float64) - np.asarray(reference, np.float64)) ** 2)))


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


def image_metrics(image: np.ndarray, reference: np.ndarray, lpips: dict | None = None) -> dict[str, float]:
    """All per-image figures: psnr (dB), ssim (data_range 1), dssim1, dssim2, and lpips_<net> for each
    network of `lpips` (lpips_models' dict)."""
    s1, s2 = ssim(image, reference, 1.0), ssim(image, reference, 2.0)
    figures = {"psnr": psnr(image, reference), "ssim": s1, "dssim1": (1 - s1) / 2, "dssim2": (1 - s2) / 2}
    for net, network in (lpips or {}).items():
        figures[f"lpips_{net}"] = lpips_distance(network, image, reference)
    return figures


def evaluate_player(player, dataset, camera_indices=None, frames=None, lpips: dict | None = None) -> dict:
    """Render dataset cameras (default: the held-out ones) at every frame (or `frames`) through a
    stg_runtime Player and compare with the ground truth.

    Returns {"psnr", "ssim", "dssim1", "dssim2"} (and "lpips_<net>" for each network of `lpips`) means
    over the images, "fps" (images rendered per second of Player.render time, after one warm-up render),
    "images", "cameras" (names), "per_frame" (list of per-image figures with camera name and frame)."""
    cams = dataset.test_cameras if camera_indices is None else list(camera_indices)
    start_frame = getattr(dataset, "start_frame", 0)  # a Dataset.frame_range view: its frame j is video frame start + j
    frames = list(range(dataset.num_frames)) if frames is None else list(frames)
    if not cams or not frames:
        raise ValueError("evaluate_player: no camera or no frame to evaluate")
    player.render(dataset.cameras[cams[0]], player.start_time)  # warm-up (numba, onnxruntime)
    rows, seconds = [], 0.0
    for ci in cams:
        cam = dataset.cameras[ci]
        for j in frames:
            start = time.perf_counter()
            image = player.render(cam, (start_frame + j) / dataset.fps)
            seconds += time.perf_counter() - start
            rows.append({"camera": cam.name, "frame": j, **image_metrics(image, dataset.image(ci, j), lpips)})
    keys = ("psnr", "ssim", "dssim1", "dssim2") + tuple(f"lpips_{net}" for net in (lpips or {}))
    means = {k: float(np.mean([r[k] for r in rows])) for k in keys}
    return {**means, "fps": len(rows) / seconds if seconds > 0 else float("inf"), "images": len(rows),
            "cameras": [dataset.cameras[ci].name for ci in cams], "per_frame": rows}


def heldout(result: dict) -> dict:
    """The HELDOUT_KEYS (and LPIPS_KEYS where computed) of an evaluate_player result."""
    return {k: result[k] for k in HELDOUT_KEYS + LPIPS_KEYS if k in result}
