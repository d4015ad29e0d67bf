"""Raw trainable parameters -> Gaussians at tau (stg_train.params.gaussians_at), and -> the file's
attributes (stg_train.raw.to_file_arrays)."""
import numpy as np
import pytest

torch = pytest.importorskip("torch")

from stg_runtime.model import ATTRIBUTES, Segment  # noqa: E402
from stg_runtime.onnx_mlp import mlp_to_onnx  # noqa: E402
from stg_runtime.spec import evaluate_oracle  # noqa: E402
from stg_train.params import gaussians_at as evaluate  # noqa: E402
from stg_train.params import temporal_opacity  # noqa: E402
from stg_train.raw import to_file_arrays  # noqa: E402

DECODER = mlp_to_onnx([np.ones((6, 12), np.float32), np.ones((3, 6), np.float32)])


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
    arrays = to_file_arrays({k: v.numpy() for k, v in raw.items()}, dtype=np.float64)
    assert set(arrays) == set(ATTRIBUTES)
    n = raw["xyz"].shape[0]
    assert arrays["position"].shape == (n, 4, 3) and arrays["rotation"].shape == (n, 2, 4)
    assert arrays["features"].shape == (n, 9 if full else 3)
    seg = Segment(0, 50, decoder=DECODER if full else None, **arrays)
    for name, value in arrays.items():  # Segment stores float32; compare against the float64 values
        setattr(seg, name, value)
    ref = evaluate_oracle(seg, tau)
    got = evaluate(raw, tau)
    for name in ("means", "quats", "scales", "opacities", "features"):
        np.testing.assert_allclose(getattr(got, name).detach().numpy(), ref[name], rtol=1e-10, atol=1e-10, err_msg=name)


def test_file_arrays_default_to_float32():
    arrays = to_file_arrays({k: v.numpy() for k, v in _raw(n=5).items()})
    assert all(a.dtype == np.float32 for a in arrays.values())
    Segment(0, 50, decoder=DECODER, **arrays)  # valid shapes


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


# -- STGParams ---------------------------------------------------------------------------------------
from stg_train.params import (COMPONENTS, STATIC_T_SCALE, LearningRates, STGParams, extent_of,  # noqa: E402
                              knn_mean_sq_dist, position_lr)


def _points(n=50, seed=0):
    rng = np.random.default_rng(seed)
    return rng.normal(size=(n, 3)) + [0, 0, 5], rng.uniform(0.05, 0.95, (n, 3)), rng.uniform(0, 1, n)


def test_initial_values_follow_the_reference():
    xyz, rgb, t_center = _points()
    full = STGParams.from_points(xyz, rgb, t_center, "full")
    assert full.count == 50 and set(full.raw) == set(STGParams.names("full"))
    np.testing.assert_allclose(full["xyz"].detach().numpy(), xyz, rtol=1e-6)
    np.testing.assert_allclose(full["t_center"].detach().numpy()[:, 0], t_center, rtol=1e-6)
    np.testing.assert_allclose(torch.sigmoid(full["features"][:, :3]).detach().numpy(), rgb, atol=1e-5)  # logit
    np.testing.assert_allclose(torch.sigmoid(full["opacity_logit"]).detach().numpy(), 0.1, rtol=1e-5)
    assert torch.equal(full["rotation"], torch.tensor([[1.0, 0, 0, 0]]).expand(50, 4))
    assert not full["motion"].any() and not full["omega"].any() and not full["t_scale_raw"].any()
    # scale: the root mean squared distance to the 3 nearest points, the same on every axis
    d2 = ((xyz[:, None] - xyz[None]) ** 2).sum(-1) + np.diag(np.full(50, np.inf))
    want = np.sqrt(np.sort(d2, axis=1)[:, :3].mean(1))
    np.testing.assert_allclose(torch.exp(full["log_scale"]).detach().numpy(), np.repeat(want[:, None], 3, 1),
                               rtol=1e-5)
    lite = STGParams.from_points(xyz, rgb, t_center, "lite")
    assert "time_features" not in lite.raw and lite.decoder is None
    np.testing.assert_allclose(lite["features"].detach().numpy(), rgb, rtol=1e-6)  # plain rgb


def test_frozen_components_are_not_optimised():
    xyz, rgb, t_center = _points(n=10)
    params = STGParams.from_points(xyz, rgb, t_center, "full", frozen=("motion", "temporal_opacity"))
    groups = {g["name"] for g in params.param_groups(LearningRates(), 1.0)}
    assert "motion" not in groups and "t_center" not in groups and "t_scale_raw" not in groups
    assert {"xyz", "omega", "time_features", "decoder"} <= groups
    assert torch.all(params["t_scale_raw"] == STATIC_T_SCALE)  # temporal opacity 1 at every time
    opacity = params.at(0.0).opacities.detach()
    torch.testing.assert_close(opacity, params.at(1.0).opacities.detach())
    static = STGParams.from_points(xyz, rgb, t_center, "lite", static=True)
    assert static.static and static.frozen == tuple(sorted(COMPONENTS))
    with pytest.raises(ValueError, match="unknown component"):
        STGParams.from_points(xyz, rgb, t_center, "full", frozen=("colour",))


def test_state_dict_round_trip_keeps_values_decoder_and_frozen():
    xyz, rgb, t_center = _points(n=8)
    params = STGParams.from_points(xyz, rgb, t_center, "full", frozen=("rotation",), seed=4)
    again = STGParams.from_state_dict(params.state_dict())
    assert again.kind == "full" and again.frozen == ("rotation",)
    for name in params.raw:
        assert torch.equal(params[name], again[name]) and params[name].requires_grad == again[name].requires_grad
    for a, b in zip(params.decoder.weights(), again.decoder.weights()):
        np.testing.assert_array_equal(a, b)


def test_new_rows_take_their_scale_from_existing_neighbours():
    xyz, rgb, t_center = _points(n=30)
    params = STGParams.from_points(xyz, rgb, t_center, "full")
    new = params.new_rows(torch.tensor([[0.0, 0.0, 5.0]]), torch.tensor([[0.2, 0.4, 0.6]]), torch.tensor([0.3]),
                          opacity=0.25)
    assert set(new) == set(params.raw) and all(v.shape[0] == 1 for v in new.values())
    d2 = np.sort(((xyz - [0, 0, 5]) ** 2).sum(1))[:3].mean()
    torch.testing.assert_close(torch.exp(new["log_scale"]), torch.full((1, 3), float(np.sqrt(d2))))
    torch.testing.assert_close(torch.sigmoid(new["opacity_logit"]), torch.tensor([[0.25]]))


def test_knn_matches_brute_force():
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(300, 3))
    pts[10] = pts[11]  # a duplicate counts as a neighbour at distance 0
    d2 = ((pts[:, None] - pts[None]) ** 2).sum(-1)
    np.fill_diagonal(d2, np.inf)
    want = np.sort(d2, 1)[:, :3].mean(1)
    got = knn_mean_sq_dist(torch.tensor(pts, dtype=torch.float32).double(), k=3)
    np.testing.assert_allclose(got.numpy(), want, rtol=1e-6)
    np.testing.assert_allclose(knn_mean_sq_dist(torch.tensor(pts), k=3, rows=40).numpy(), want[:40], rtol=1e-6)


def test_knn_extent_and_position_rate():
    points = torch.tensor([[0.0, 0, 0], [1, 0, 0], [3, 0, 0]])
    torch.testing.assert_close(knn_mean_sq_dist(points, k=1), torch.tensor([1.0, 1.0, 4.0]))
    from stg_runtime.camera import Camera
    cams = [Camera(10, 10, 5, 5, 10, 10, np.eye(4))]
    moved = np.eye(4)
    moved[0, 3] = -2.0  # camera centre at x = 2
    cams.append(Camera(10, 10, 5, 5, 10, 10, moved))
    assert extent_of(cams) == pytest.approx(1.1)
    lr = LearningRates()
    assert position_lr(lr, 2.0, 0, 100) == pytest.approx(2.0 * lr.xyz_init)
    assert position_lr(lr, 2.0, 100, 100) == pytest.approx(2.0 * lr.xyz_final)
    assert position_lr(lr, 2.0, 50, 100) == pytest.approx(2.0 * np.sqrt(lr.xyz_init * lr.xyz_final))
