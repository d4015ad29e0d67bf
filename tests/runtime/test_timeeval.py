"""Time evaluation (formats/stg-v1.md section 2) against a float64 transcription of the formulas."""
import numpy as np
import pytest

from stg_runtime.model import Segment
from stg_runtime.onnx_mlp import mlp_to_onnx
from stg_runtime.spec import MIN_ALPHA, evaluate_oracle
from stg_runtime.timeeval import evaluate

DECODER = mlp_to_onnx([np.ones((6, 12), np.float32), np.ones((3, 6), np.float32)])


def _segment(n=300, kind="full", p=3, q=1, seed=0):
    rng = np.random.default_rng(seed)
    c = 9 if kind == "full" else 3
    return Segment(0, 50, opacity=rng.uniform(0, 1, n), t_center=rng.uniform(0, 1, n), t_scale=rng.uniform(0, 30, n),
                   position=rng.standard_normal((n, p + 1, 3)), rotation=rng.standard_normal((n, q + 1, 4)),
                   scale=rng.uniform(0.01, 1, (n, 3)), features=rng.standard_normal((n, c)),
                   decoder=DECODER if kind == "full" else None)


@pytest.mark.parametrize("kind,p,q", [("full", 3, 1), ("lite", 3, 1), ("full", 1, 0), ("lite", 5, 2)])
@pytest.mark.parametrize("tau", [0.0, 0.37, 1.0])
def test_matches_float64_formula(kind, p, q, tau):
    seg = _segment(kind=kind, p=p, q=q)
    got = evaluate(seg, tau)
    ref = evaluate_oracle(seg, tau)
    keep = ref["opacities"] >= MIN_ALPHA
    np.testing.assert_array_equal(got.index, np.flatnonzero(keep))
    for name in ("means", "quats", "scales", "opacities", "features"):
        np.testing.assert_allclose(getattr(got, name), ref[name][keep], rtol=2e-5, atol=2e-5, err_msg=name)


def test_hand_computed_values():
    # One Gaussian: b = (1,2,3) + (1,0,0) d + (0,1,0) d^2 + (0,0,1) d^3; rotation (1,0,0,0) + (0,0,0,2) d.
    pos = np.array([[[1, 2, 3], [1, 0, 0], [0, 1, 0], [0, 0, 1]]], float)
    rot = np.array([[[1, 0, 0, 0], [0, 0, 0, 2]]], float)
    feats = np.arange(1, 10, dtype=float)[None]
    seg = Segment(0, 10, opacity=[0.8], t_center=[0.25], t_scale=[4.0], position=pos, rotation=rot,
                  scale=[[1, 2, 3]], features=feats, decoder=DECODER)
    g = evaluate(seg, 0.75)  # d = 0.5
    assert g.opacities[0] == pytest.approx(0.8 * np.exp(-4.0 * 0.25))
    np.testing.assert_allclose(g.means[0], [1.5, 2.25, 3.125], rtol=1e-6)
    np.testing.assert_allclose(g.quats[0], np.array([1, 0, 0, 1]) / np.sqrt(2), rtol=1e-6)
    np.testing.assert_allclose(g.features[0], [1, 2, 3, 4, 5, 6, 3.5, 4, 4.5], rtol=1e-6)


def test_faded_gaussians_are_dropped():
    seg = _segment(2000, "lite", seed=3)
    g = evaluate(seg, 0.0)
    full = seg.opacity * np.exp(-seg.t_scale * seg.t_center.astype(np.float64) ** 2)
    assert 0 < len(g.index) < seg.count
    assert np.all(full[g.index] >= MIN_ALPHA) and np.all(np.delete(full, g.index) < MIN_ALPHA)
