"""stg_train.metrics' dynamic / static regions on constructed cases where the mask and the figures are
known exactly: a static camera whose ground truth changes in one block (by 0.6, above the threshold)
and in another only by 0.05 (below it); renders off by 0.1 on the dynamic pixels and by 0.01 on the
static ones, so PSNR is exactly 20 dB and 40 dB there."""
from __future__ import annotations

import types

import numpy as np
import pytest

from stg_train import metrics

H, W, FRAMES = 24, 32, 4
MOVING = (slice(4, 12), slice(6, 16))     # changes by 0.6 over the clip: dynamic
FLICKER = (slice(16, 22), slice(20, 30))  # changes by 0.05: below the threshold, static


def ground_truth(j: int) -> np.ndarray:
    image = np.full((H, W, 3), 0.5)
    image[MOVING] = 0.2 if j % 2 == 0 else 0.8
    image[FLICKER] = 0.5 + 0.05 * (j % 2)
    image[..., 2] *= 0.9  # channels differ; the changes above stay the largest per pixel
    return image


def expected_mask() -> np.ndarray:
    mask = np.zeros((H, W), bool)
    mask[MOVING] = True
    return mask


def render(j: int) -> np.ndarray:
    """The ground truth off by exactly 0.1 on the dynamic pixels and 0.01 on the static ones."""
    return ground_truth(j) + np.where(expected_mask()[..., None], 0.1, 0.01)


def test_mask_is_the_pixels_changing_by_more_than_the_threshold():
    frames = [ground_truth(j) for j in range(FRAMES)]
    mask = metrics.dynamic_mask(frames)
    assert mask.shape == (H, W) and mask.dtype == bool
    np.testing.assert_array_equal(mask, expected_mask())
    assert metrics.dynamic_mask(frames, threshold=0.04)[FLICKER].all()  # a lower threshold takes the flicker
    assert not metrics.dynamic_mask(frames, threshold=0.7).any()
    assert not metrics.dynamic_mask([ground_truth(0)] * 3).any()  # nothing changes: nothing dynamic
    with pytest.raises(ValueError, match="no frames"):
        metrics.dynamic_mask([])


def test_region_psnr_is_exact_and_whole_image_consistent():
    mask = expected_mask()
    figures = metrics.image_metrics(render(0), ground_truth(0), dynamic=mask)
    assert figures["dynamic_psnr"] == pytest.approx(20.0, abs=1e-9)
    assert figures["static_psnr"] == pytest.approx(40.0, abs=1e-9)
    f = mask.mean()
    assert figures["psnr"] == pytest.approx(-10 * np.log10(f * 0.01 + (1 - f) * 1e-4), abs=1e-9)


def test_region_ssim_over_all_pixels_is_ssim_and_far_errors_do_not_count():
    rng = np.random.default_rng(0)
    a, b = rng.uniform(0, 1, (H, W, 3)), rng.uniform(0, 1, (H, W, 3))
    everything = metrics.region_metrics(a, b, np.ones((H, W), bool))
    assert everything["ssim"] == pytest.approx(metrics.ssim(a, b), abs=1e-12)
    assert everything["psnr"] == pytest.approx(metrics.psnr(a, b), abs=1e-12)
    # an error far (more than the 7x7 window) from the dynamic block: the dynamic SSIM stays exactly 1
    gt = ground_truth(0) + rng.uniform(-0.05, 0.05, (H, W, 3))
    image = gt.copy()
    image[18:, 22:] += 0.2
    figures = metrics.image_metrics(image, gt, dynamic=expected_mask())
    assert figures["dynamic_ssim"] == pytest.approx(1.0, abs=1e-12) and figures["dynamic_psnr"] == float("inf")
    assert figures["static_ssim"] < 0.99
    # empty regions have no figures; a mask only within the SSIM border has a PSNR but no SSIM
    assert metrics.region_metrics(a, b, np.zeros((H, W), bool)) == {"psnr": None, "ssim": None}
    edge = np.zeros((H, W), bool)
    edge[0, :] = True
    assert metrics.region_metrics(a, b, edge)["ssim"] is None and metrics.region_metrics(a, b, edge)["psnr"] > 0


def test_evaluate_player_reports_both_regions():
    class Player:
        start_time = 0.0

        def render(self, camera, t):
            return render(int(round(t)))

    class Dataset:
        test_cameras, num_frames, fps = [0], FRAMES, 1.0
        cameras = [types.SimpleNamespace(name="cam00")]

        def image(self, ci, j):
            return ground_truth(j)

    result = metrics.evaluate_player(Player(), Dataset())
    assert result["dynamic_psnr"] == pytest.approx(20.0, abs=1e-9)
    assert result["static_psnr"] == pytest.approx(40.0, abs=1e-9)
    assert result["dynamic_fraction"] == pytest.approx(expected_mask().mean())
    assert result["dynamic_threshold"] == metrics.DYNAMIC_THRESHOLD
    assert all(r["dynamic_psnr"] == pytest.approx(20.0) for r in result["per_frame"])
    held = metrics.heldout(result)
    assert held["dynamic_psnr"] == result["dynamic_psnr"] and held["static_ssim"] == result["static_ssim"]
    # over frames 0 and 2 only, the ground truth never changes: no dynamic pixel
    still = metrics.evaluate_player(Player(), Dataset(), frames=[0, 2])
    assert still["dynamic_fraction"] == 0 and still["dynamic_psnr"] is None
    assert still["static_psnr"] == pytest.approx(still["psnr"])


def test_segments_pool_region_figures_by_images():
    from stg_train.segments import pooled

    base = {"psnr": 30.0, "ssim": 0.9, "dssim1": 0.05, "dssim2": 0.02, "fps": 10.0, "cameras": ["cam00"],
            "static_psnr": 32.0, "static_ssim": 0.95, "dynamic_fraction": 0.2, "dynamic_threshold": 0.1}
    a = {**base, "images": 3, "dynamic_psnr": 20.0, "dynamic_ssim": 0.5}
    b = {**base, "images": 1, "dynamic_psnr": 24.0, "dynamic_ssim": 0.9}
    c = {**base, "images": 4, "dynamic_psnr": None, "dynamic_ssim": None, "dynamic_fraction": 0.0}
    out = pooled([a, b, c])
    assert out["dynamic_psnr"] == pytest.approx(21.0) and out["dynamic_ssim"] == pytest.approx(0.6)
    assert out["static_psnr"] == pytest.approx(32.0) and out["dynamic_fraction"] == pytest.approx(0.1)
    assert pooled([c])["dynamic_psnr"] is None
