"""stg_train.metrics: PSNR / SSIM / DSSIM and the optional LPIPS. The lpips package is not installed
here (its torchvision does not import beside the CPU torch build), so LPIPS's code path is tested with a
stand-in package whose networks are known functions: what they receive (range, layout) and how the
figures are averaged."""
from __future__ import annotations

import sys
import types

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from stg_train import metrics  # noqa: E402


class _Net(torch.nn.Module):
    """A stand-in LPIPS network: mean |a - b| times a per-network factor; remembers its inputs."""

    def __init__(self, net, version, verbose):
        super().__init__()
        self.factor = {"alex": 1.0, "vgg": 10.0}[net]
        self.seen = []

    def forward(self, a, b):
        self.seen.append((a.clone(), b.clone()))
        return self.factor * (a - b).abs().mean(dim=(1, 2, 3), keepdim=True)


def _fake_lpips(monkeypatch, fail=None):
    module = types.ModuleType("lpips")

    def make(net, version, verbose):
        if fail:
            raise fail
        return _Net(net, version, verbose)
    module.LPIPS = make
    monkeypatch.setitem(sys.modules, "lpips", module)


def test_lpips_inputs_range_layout_and_averaging(monkeypatch):
    _fake_lpips(monkeypatch)
    models, why = metrics.lpips_models()
    assert why is None and set(models) == {"alex", "vgg"}
    rng = np.random.default_rng(0)
    a, b = rng.uniform(0, 1, (12, 16, 3)), rng.uniform(0, 1, (12, 16, 3))
    figures = metrics.image_metrics(a, b, lpips=models)
    (x, y), = models["alex"].seen
    assert x.shape == (1, 3, 12, 16) and x.dtype == torch.float32
    assert x.min() >= -1 and x.max() <= 1 and x.min() < -0.9 and x.max() > 0.9  # [0, 1] -> [-1, 1]
    np.testing.assert_allclose(x[0].permute(1, 2, 0).numpy(), 2 * a - 1, atol=1e-6)
    np.testing.assert_allclose(figures["lpips_alex"], 2 * np.abs(a - b).mean(), rtol=1e-5)
    np.testing.assert_allclose(figures["lpips_vgg"], 20 * np.abs(a - b).mean(), rtol=1e-5)
    assert {"psnr", "ssim", "dssim1", "dssim2"} <= set(figures)


def test_lpips_missing_says_why(monkeypatch):
    monkeypatch.setitem(sys.modules, "lpips", None)  # not installed
    models, why = metrics.lpips_models()
    assert models == {} and why.startswith("LPIPS not computed: the lpips package cannot be imported")
    _fake_lpips(monkeypatch, fail=OSError("urlopen error [Errno -3] Temporary failure in name resolution"))
    models, why = metrics.lpips_models()
    assert models == {} and "alex network cannot be loaded" in why and "name resolution" in why


def test_evaluation_means_and_held_out_keys(monkeypatch):
    _fake_lpips(monkeypatch)
    models, _ = metrics.lpips_models()

    class Player:
        start_time = 0.0

        def render(self, camera, t):
            return np.full((8, 8, 3), 0.5 + 0.1 * t, np.float32)

    class Dataset:
        test_cameras, num_frames, fps = [0], 3, 1.0
        cameras = [types.SimpleNamespace(name="cam00")]

        def image(self, ci, j):
            return np.full((8, 8, 3), 0.5, np.float32)

    result = metrics.evaluate_player(Player(), Dataset(), lpips=models)
    np.testing.assert_allclose([r["lpips_alex"] for r in result["per_frame"]], [0.0, 0.2, 0.4], atol=1e-6)
    assert result["lpips_alex"] == pytest.approx(0.2, abs=1e-6) and result["lpips_vgg"] == pytest.approx(2.0, abs=1e-5)
    assert set(metrics.heldout(result)) == set(metrics.HELDOUT_KEYS + metrics.REGION_KEYS + metrics.LPIPS_KEYS)
    plain = metrics.evaluate_player(Player(), Dataset())
    assert set(metrics.heldout(plain)) == set(metrics.HELDOUT_KEYS + metrics.REGION_KEYS)  # no LPIPS: no LPIPS keys
    # the ground truth never changes: no dynamic pixel, so no dynamic figures
    assert plain["dynamic_fraction"] == 0 and plain["dynamic_psnr"] is None and plain["dynamic_ssim"] is None
    assert plain["static_psnr"] == pytest.approx(plain["psnr"])


def test_psnr_and_dssim():
    a = np.zeros((4, 4, 3))
    assert metrics.psnr(a, a) == float("inf") and metrics.psnr(a, a + 0.1) == pytest.approx(20.0)
    assert metrics.psnr_of_mse(1e-4) == pytest.approx(40.0)
    rng = np.random.default_rng(1)
    b = rng.uniform(0, 1, (16, 16, 3))
    assert metrics.dssim1(b, b) == pytest.approx(0.0, abs=1e-12) and metrics.dssim1(b, 1 - b) > 0.1


def test_aligned_psnr_undoes_one_affine_colour_map_per_camera():
    rng = np.random.default_rng(0)
    truth = [rng.uniform(0.1, 0.9, (12, 16, 3)) for _ in range(3)]
    gain = np.array([[0.9, 0.05, 0.0], [0.0, 1.1, 0.02], [0.03, 0.0, 0.8]])
    bias = np.array([0.02, -0.03, 0.05])
    renders = [t @ gain.T + bias for t in truth]  # a camera that sees the scene through one colour map
    exact = metrics.aligned_psnrs([metrics.affine_moments(r, t) for r, t in zip(renders, truth)])
    assert all(value > 100 for value in exact)  # the map is found: no error is left
    assert all(metrics.psnr(r, t) < 35 for r, t in zip(renders, truth))
    # with a different map per frame, one map per camera cannot undo them all
    varied = [t * (1 + 0.1 * k) for k, t in enumerate(truth)]
    assert max(metrics.aligned_psnrs([metrics.affine_moments(r, t) for r, t in zip(varied, truth)])) < 60
    # the fit is at least as good as no map at all
    noisy = [t + rng.normal(0, 0.02, t.shape) for t in truth]
    aligned = metrics.aligned_psnrs([metrics.affine_moments(r, t) for r, t in zip(noisy, truth)])
    assert np.mean(aligned) >= np.mean([metrics.psnr(r, t) for r, t in zip(noisy, truth)]) - 1e-9


def test_temporal_errors_measure_a_pop_not_a_steady_offset():
    rng = np.random.default_rng(0)
    truth = rng.random((5, 4, 6, 3))
    steady = truth + 0.1  # a constant error follows the true change: no temporal error
    np.testing.assert_allclose(metrics.temporal_errors(steady, truth), 0.0, atol=1e-12)
    popped = truth.copy()
    popped[3:] += 0.2  # a jump of 0.2 between frames 2 and 3 only
    np.testing.assert_allclose(metrics.temporal_errors(popped, truth), [0, 0, 0.2, 0], atol=1e-12)
    with pytest.raises(ValueError, match="two equal"):
        metrics.temporal_errors(popped[:1], truth[:1])


def test_seam_figures_boundaries_dip_and_flicker():
    psnrs = [30.0, 31, 31, 29.5, 30, 31, 31, 30.8]  # segments [0, 4) and [4, 8)
    pairs = [0.01, 0.01, 0.01, 0.04, 0.01, 0.01, 0.01]
    f = metrics.seam_figures(psnrs, pairs, [0, 4])
    assert f["boundary"] == {0: 30.0, 3: 29.5, 4: 30.0, 7: 30.8}
    assert f["interior_psnr"] == pytest.approx(31.0)
    assert f["worst_dip"] == pytest.approx(1.5)
    assert f["seams"] == {4: pytest.approx(0.04)}
    assert f["interior_pair_error"] == pytest.approx(0.01)
    assert f["flicker_ratio"] == pytest.approx(4.0)
    assert metrics.seam_figures(psnrs, pairs, [0])["flicker_ratio"] is None
    with pytest.raises(ValueError, match="do not cut"):
        metrics.seam_figures(psnrs, pairs, [1, 4])


def test_evaluate_seams_finds_the_pop_between_two_segments():
    from types import SimpleNamespace

    from stg_runtime.camera import Camera
    from stg_train.data.dataset import Dataset

    rng = np.random.default_rng(1)
    frames = (rng.random((1, 6, 8, 10, 3)) * 200).astype(np.uint8)  # 1 camera x 6 frames
    cam = Camera.from_opencv(np.array([[10.0, 0, 5], [0, 10, 4], [0, 0, 1]]), np.eye(4), 10, 8, name="cam00")
    data = Dataset([cam], frames, 30.0, test_cameras=[0])

    def render(camera, t):  # segment 0 (frames 0-2) brighter by 0.05 (26.02 dB), segment 1 by 0.1 (20 dB)
        j = int(round(t * 30.0))
        return data.image(0, j).astype(np.float64) + (0.1 if j >= 3 else 0.05)

    player = SimpleNamespace(render=render, start_time=0.0, model=SimpleNamespace(segments=[SimpleNamespace(start_frame=0),
                                                                                            SimpleNamespace(start_frame=3)]))
    result = metrics.evaluate_player(player, data)
    seams = metrics.evaluate_seams(result, [0, 3])
    assert seams["seams"] == {3: pytest.approx(0.05)}
    assert seams["interior_pair_error"] == pytest.approx(0.0, abs=1e-9)
    assert set(seams["boundary"]) == {0, 2, 3, 5}
    assert seams["interior_psnr"] == pytest.approx((26.0206 + 20.0) / 2, abs=1e-3)  # frames 1 and 4
    assert seams["worst_dip"] == pytest.approx(3.0103, abs=1e-3)
    assert [r["temporal_error"] for r in result["per_frame"]][0] is None  # no pair ends at the first frame
    one = metrics.evaluate_player(player, data, frames=range(0, 3))
    assert metrics.evaluate_seams(one, [0, 3]) is None  # frames of one segment: no seam
    ends = metrics.evaluate_seams(one, [0, 3], require_seam=False)  # ... but its ends against its interior
    assert set(ends["boundary"]) == {0, 2} and ends["seams"] == {} and ends["flicker_ratio"] is None
    assert ends["worst_dip"] == pytest.approx(0.0, abs=1e-9)  # every frame of segment 0 is at 26.02 dB
