"""stg_train.timeeval: raw trainable parameters -> Gaussians at tau, and -> the file's attributes."""
import numpy as np
import pytest

torch = pytest.importorskip("torch")

from stg_runtime.model import ATTRIBUTES, Segment  # noqa: E402
from stg_runtime.spec import evaluate_oracle  # noqa: E402
from stg_train.timeeval import evaluate, temporal_opacity, to_file_arrays  # noqa: E402


def _raw(n=200, full=True, seed=0, requires_grad=False):
    rng = np.random.default_rng(seed)
    raw = {
        "xyz": rng.standard_normal((n, 3)),
        "motion": rng.standard_normal((n, 9)),
        "rotation": rng.standard_normal((n, 4)),
        "omega": rng.standard_normal((n, 4)),
        "log_scale": rng.uniform(-4, 0, (n, 3)),
        "opacity_logit": rng.uniform(-4, 4, (n, 1)),
        "t_center": rng.uniform(0, 1, n),
        "t_scale_raw": rng.uniform(-2, 1, n),
        "features": rng.standard_normal((n, 6 if full else 3)),
    }
    if full:
        raw["time_features"] = rng.standard_normal((n, 3))
    return {k: torch.tensor(v, dtype=torch.float64, requires_grad=requires_grad) for k, v in raw.items()}


@pytest.mark.parametrize("full", [True, False])
@pytest.mark.parametrize("tau", [0.0, 0.41, 0.98])
def test_matches_file_formula(full, tau):
    raw = _raw(full=full)
    arrays = to_file_arrays(raw, dtype=np.float64)
    assert set(arrays) == set(ATTRIBUTES)
    n = raw["xyz"].shape[0]
    assert arrays["position"].shape == (n, 4, 3) and arrays["rotation"].shape == (n, 2, 4)
    assert arrays["features"].shape == (n, 9 if full else 3)
    seg = Segment(0, 50, decoder=b"" if full else None, **arrays)
    for name, value in arrays.items():  # Segment stores float32; compare against the float64 values
        setattr(seg, name, value)
    ref = evaluate_oracle(seg, tau)
    got = evaluate(raw, tau)
    for name in ("means", "quats", "scales", "opacities", "features"):
        np.testing.assert_allclose(getattr(got, name).detach().numpy(), ref[name], rtol=1e-10, atol=1e-10, err_msg=name)


def test_file_arrays_default_to_float32():
    arrays = to_file_arrays(_raw(n=5))
    assert all(a.dtype == np.float32 for a in arrays.values())
    Segment(0, 50, decoder=b"", **arrays)  # valid shapes


def test_only_temporal_opacity_reaches_t_center():
    raw = _raw(n=20, requires_grad=True)
    g = evaluate(raw, 0.3)
    (g.means.sum() + g.quats.sum() + g.features.sum()).backward()
    assert raw["t_center"].grad is None or raw["t_center"].grad.abs().max() == 0
    assert raw["motion"].grad.abs().max() > 0 and raw["omega"].grad.abs().max() > 0
    raw["t_center"].grad = None
    temporal_opacity(raw, 0.3).sum().backward()
    assert raw["t_center"].grad.abs().min() > 0


def test_reference_activation():
    raw = _raw(n=10)
    tau = 0.7
    dt = tau - raw["t_center"]
    want = torch.sigmoid(raw["opacity_logit"][:, 0]) * torch.exp(-(dt / torch.exp(raw["t_scale_raw"])) ** 2)
    torch.testing.assert_close(evaluate(raw, tau).opacities, want, rtol=1e-12, atol=0)
