"""stg_train.strategy.density: clone, split, prune, opacity reset and the schedule, on hand-made
statistics (the full training loop is in tests/train/test_pipeline.py)."""
from __future__ import annotations

import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")
from torch import Tensor  # noqa: E402

from stg_runtime.camera import Camera  # noqa: E402
from stg_train.params import LearningRates, STGParams  # noqa: E402
from stg_train.render import RenderOutput  # noqa: E402
from stg_train.strategy import DensityControl, Schedule, StepContext, Thresholds  # noqa: E402


def _setup(n=20, seed=0, extent=1.0, **schedule):
    rng = np.random.default_rng(seed)
    params = STGParams.from_points(rng.normal(size=(n, 3)) + [0, 0, 4], rng.uniform(0.1, 0.9, (n, 3)),
                                   rng.uniform(0, 1, n), "lite", seed=seed)
    optimizer = torch.optim.Adam(params.param_groups(LearningRates(), extent), eps=1e-15)
    return params, optimizer, DensityControl(Schedule(**schedule), extent)


def _set(params, optimizer, name, value):
    from stg_train.strategy.ops import set_values
    set_values(params, optimizer, name, torch.as_tensor(value, dtype=torch.float32))


def test_prune_removes_faint_gaussians_and_their_statistics():
    params, optimizer, dc = _setup()
    logit = torch.full((20, 1), 0.0)
    logit[[3, 7, 11]] = math.log(0.004 / 0.996)  # below prune_opacity 0.005
    _set(params, optimizer, "opacity_logit", logit)
    dc._fit(params.count)
    dc.prune(params, optimizer, step=600)
    assert params.count == 17 and dc.grad_sum.shape == (17,)
    assert dc.log[-1] == {"step": 600, "pruned": 3, "count": 17}
    assert torch.all(torch.sigmoid(params["opacity_logit"]) >= 0.005)


def test_densify_clones_small_and_splits_large_hot_gaussians():
    params, optimizer, dc = _setup(extent=1.0)
    log_scale = torch.full((20, 3), math.log(0.005))  # small: <= percent_dense 0.01 x extent
    log_scale[10:] = math.log(0.05)  # large
    _set(params, optimizer, "log_scale", log_scale)
    dc._fit(params.count)
    hot = torch.zeros(20, dtype=torch.bool)
    hot[[0, 1, 12, 13, 14]] = True  # 2 small, 3 large
    dc.grad_sum[hot] = 10 * dc.thresholds.grad
    dc.grad_count[:] = 10
    parents = params["xyz"].detach()[[12, 13, 14]].clone()
    torch.manual_seed(0)
    dc.densify_and_prune(params, optimizer, step=600)
    assert dc.log[-1] == {"step": 600, "cloned": 2, "split": 3, "pruned": 0, "count": 20 + 2 + 6 - 3}
    xyz = params["xyz"].detach()
    assert params.count == 25 and dc.grad_sum.shape == (25,) and torch.all(dc.grad_sum == 0)
    # the split parents are gone; the children are scaled by 1 / split_scale around them
    for p in parents:
        assert not torch.any(torch.all(xyz == p, dim=1))
    children = params["log_scale"].detach()[-6:]
    torch.testing.assert_close(children, torch.full((6, 3), math.log(0.05) - math.log(1.6)))
    # the clones copy their originals' positions
    assert torch.equal(xyz[-8:-6], xyz[:2])


def test_reset_opacity_caps_at_the_threshold():
    params, optimizer, dc = _setup()
    dc.reset_opacity(params, optimizer)
    opacity = torch.sigmoid(params["opacity_logit"].detach())
    assert torch.all(opacity <= Thresholds().reset_opacity + 1e-7)


def test_screen_gradients_are_normed_per_view_in_ndc_units():
    params, optimizer, dc = _setup(n=3)
    camera = Camera(50, 50, 20, 15, 40, 30, np.eye(4))
    means2d = torch.zeros(3, 2, requires_grad=True)
    means2d.grad = torch.tensor([[1.0, 0.0], [0.0, 2.0], [0.0, 0.0]])
    out = RenderOutput(None, None, None, means2d, torch.tensor([3, 4, 0]), torch.tensor([True, True, False]))
    dc.accumulate([(camera, out), (camera, out)], 0.25)
    # pixels -> NDC: times (W/2, H/2); each view's gradient times the batch size 2, normed, counted per view
    torch.testing.assert_close(dc.grad_sum, torch.tensor([2 * 2 * 20.0, 2 * 2 * 2 * 15.0, 0.0]))
    torch.testing.assert_close(dc.grad_count, torch.tensor([2.0, 2.0, 0.0]))
    torch.testing.assert_close(dc.max_radius, torch.tensor([3.0, 4.0, 0.0]))


def _statistic(batch: int, statistic: str) -> Tensor:
    """The mean densification statistic of 2 Gaussians after one step whose loss is the mean over
    `batch` views of a per-view loss that gives each Gaussian a screen gradient of norm 1 px, pointing
    in another direction in each view (views are different image planes). The camera is square, so
    1 px is 20 NDC units in every direction."""
    params, optimizer, _ = _setup(n=2)
    dc = DensityControl(Schedule(), 1.0, Thresholds(grad_statistic=statistic))
    camera = Camera(50, 50, 20, 20, 40, 40, np.eye(4))
    renders, losses = [], []
    for v in range(batch):
        angle = 2 * math.pi * v / batch
        means2d = torch.zeros(2, 2, requires_grad=True)
        losses.append((means2d * torch.tensor([math.cos(angle), math.sin(angle)])).sum())
        renders.append((camera, RenderOutput(None, None, None, means2d, torch.ones(2), torch.ones(2, dtype=torch.bool))))
    torch.stack(losses).mean().backward()  # as loss_fn: the mean over the batch's views
    dc.accumulate(renders, 0.0)
    return dc.grad_sum / dc.grad_count


@pytest.mark.parametrize("batch", [1, 2, 4])
def test_the_statistic_does_not_depend_on_the_batch_size(batch):
    # every view's full-size loss gives 1 px = 20 NDC units, as the reference's one-view backward does
    torch.testing.assert_close(_statistic(batch, "per-view"), torch.tensor([20.0, 20.0]))


def test_the_summed_statistic_shrinks_with_the_batch():
    # the old statistic: the views' gradients, each 1 / B of a full one, cancel before the norm
    assert float(_statistic(1, "summed")[0]) == pytest.approx(20.0)
    assert float(_statistic(2, "summed")[0]) == pytest.approx(0.0, abs=1e-4)
    assert float(_statistic(4, "summed")[0]) == pytest.approx(0.0, abs=1e-4)


def test_the_schedule_decides_when_to_act():
    params, optimizer, dc = _setup(refine_start=2, refine_every=2, densify_rounds=1, prune_until=6, reset_every=0,
                                   outside_at=0)
    dc.thresholds = Thresholds(grad=1e9)  # nothing is hot: densification rounds only prune
    context = StepContext(None, 0, 0.0, [], None, None)
    for step in range(1, 9):
        dc.step_post_backward(params, optimizer, step, context)
    assert [entry["step"] for entry in dc.log] == [4, 6]  # after refine_start, every 2, until prune_until
    assert "cloned" in dc.log[0] and "cloned" not in dc.log[1] and dc.rounds_done == 1


def test_gaussians_removed_behind_its_back_are_an_error():
    params, optimizer, dc = _setup()
    dc._fit(20)
    with pytest.raises(RuntimeError, match="removed outside DensityControl"):
        dc._fit(19)


def test_gradient_statistics_count_only_gaussians_present_at_the_step_time():
    params, optimizer, _ = _setup(n=4)
    _set(params, optimizer, "t_center", torch.tensor([[0.0], [0.5], [0.52], [1.0]]))
    _set(params, optimizer, "t_scale_raw", torch.full((4, 1), math.log(0.05)))
    cam = Camera(50, 50, 16, 12, 32, 24, np.eye(4))
    means2d = torch.zeros(4, 2, requires_grad=True)
    (means2d * torch.tensor([1.0, 0.0])).sum().backward()  # gradient (1, 0) px for every Gaussian
    out = RenderOutput(None, None, None, means2d, torch.full((4,), 3), torch.ones(4, dtype=torch.bool))
    context = StepContext(None, 15, 0.5, [(cam, out)], None, None)
    for th, counted in ((Thresholds(), [1, 1, 1, 1]), (Thresholds(min_temporal_opacity=0.05), [0, 1, 1, 0])):
        dc = DensityControl(Schedule(refine_start=1000), 1.0, th)
        dc.step_post_backward(params, optimizer, 1, context)  # at tau 0.5: dt / s_t = 10, 0, 0.4, 10
        assert dc.grad_count.tolist() == counted
        np.testing.assert_allclose(dc.grad_sum.numpy(), 16 * np.array(counted), rtol=1e-6)  # 1 px = 16 NDC units


def test_recentred_gaussians_keep_their_trajectory():
    from stg_train.params import gaussians_at
    from stg_train.strategy.density import recentred

    params, _, _ = _setup(n=6)
    gen = torch.Generator().manual_seed(1)
    raw = {k: v.detach().clone() for k, v in params.raw.items()}
    raw["motion"] = torch.randn(6, 9, generator=gen)
    raw["omega"] = torch.randn(6, 4, generator=gen) * 0.3
    new_t = torch.rand(6, 1, generator=gen)
    moved = {**raw, **recentred(raw, new_t), "t_center": new_t}
    for tau in (0.0, 0.3, 0.9):
        before, after = gaussians_at(raw, tau), gaussians_at(moved, tau)
        torch.testing.assert_close(after.means, before.means, atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(after.quats, before.quats, atol=1e-5, rtol=1e-5)
    assert not torch.allclose(gaussians_at({**raw, "t_center": new_t}, 0.3).means, gaussians_at(raw, 0.3).means)


def _hot_at(dc, index, times, norms):
    """Feed Gaussian `index` screen gradients of the given norms (NDC units) at the given times."""
    for tau, norm in zip(times, norms):
        dc.grad_sum[index] += norm
        dc.grad_time[index] += norm * tau
        dc.grad_count[index] += 1


def test_new_gaussians_are_centred_where_their_parent_was_hot_on_its_trajectory():
    from stg_train.params import gaussians_at

    params, optimizer, dc = _setup(n=4, extent=1.0)
    dc.thresholds = Thresholds(new_t_center="gradient")  # the mean hot time (sampled: the next test)
    log_scale = torch.full((4, 3), math.log(0.005))
    log_scale[3] = math.log(0.05)  # Gaussian 3 splits, Gaussian 0 is cloned
    _set(params, optimizer, "log_scale", log_scale)
    gen = torch.Generator().manual_seed(3)
    _set(params, optimizer, "motion", torch.randn(4, 9, generator=gen))
    _set(params, optimizer, "t_center", torch.tensor([[0.5], [0.5], [0.5], [0.3]]))
    dc._fit(4)
    g = 10 * dc.thresholds.grad
    _hot_at(dc, 0, times=[0.0, 0.1, 0.9], norms=[3 * g, g, 0.0])  # weighted mean time 0.025
    _hot_at(dc, 3, times=[0.7, 0.9], norms=[g, g])  # 0.8
    parent_at = {0: gaussians_at({k: v.detach() for k, v in params.raw.items()}, 0.025).means[0],
                 3: gaussians_at({k: v.detach() for k, v in params.raw.items()}, 0.8).means[3]}
    torch.manual_seed(0)
    dc.densify_and_prune(params, optimizer, step=600)
    assert dc.log[-1]["cloned"] == 1 and dc.log[-1]["split"] == 1 and params.count == 4 - 1 + 1 + 2
    t_new = params["t_center"].detach()[-3:].reshape(-1)
    torch.testing.assert_close(t_new, torch.tensor([0.025, 0.8, 0.8]))
    raw = {k: v.detach() for k, v in params.raw.items()}
    # the clone is where its parent was at the hot time; the split children are offset from it
    torch.testing.assert_close(gaussians_at(raw, 0.025).means[-3], parent_at[0], atol=1e-5, rtol=1e-5)
    assert torch.all((raw["xyz"][-2:] - parent_at[3]).norm(dim=1) < 0.05 * 4)


def test_the_hot_time_is_the_gradient_weighted_mean_of_the_steps():
    params, optimizer, _ = _setup(n=2)
    dc = DensityControl(Schedule(refine_start=1000), 1.0, Thresholds(new_t_center="gradient"))
    cam = Camera(50, 50, 16, 12, 32, 24, np.eye(4))
    for tau, weight in ((0.0, 1.0), (1.0, 3.0)):
        means2d = torch.zeros(2, 2, requires_grad=True)
        (means2d * torch.tensor([weight, 0.0])).sum().backward()
        out = RenderOutput(None, None, None, means2d, torch.full((2,), 3), torch.ones(2, dtype=torch.bool))
        dc.step_post_backward(params, optimizer, 1, StepContext(None, 0, tau, [(cam, out)], None, None))
    torch.testing.assert_close(dc.grad_time / dc.grad_sum, torch.tensor([0.75, 0.75]))


def test_the_sampled_hot_time_is_one_of_the_steps_drawn_by_gradient():
    """new_t_center "sampled": each Gaussian keeps one step's time, drawn in proportion to its screen
    gradient there (a weighted reservoir); a parent hot at times 0 and 1 sends its copies to either,
    never to the mean 0.75 where it was not hot, and new Gaussians are centred at the sample."""
    n = 4000
    params, optimizer, _ = _setup(n=n, extent=1.0)
    dc = DensityControl(Schedule(refine_start=1000), 1.0, Thresholds(new_t_center="sampled"))
    cam = Camera(50, 50, 16, 12, 32, 24, np.eye(4))
    torch.manual_seed(0)
    for tau, weight in ((0.0, 1.0), (0.5, 0.0), (1.0, 3.0)):
        means2d = torch.zeros(n, 2, requires_grad=True)
        (means2d[:, 0] * weight).sum().backward()
        out = RenderOutput(None, None, None, means2d, torch.full((n,), 3), torch.ones(n, dtype=torch.bool))
        dc.step_post_backward(params, optimizer, 1, StepContext(None, 0, tau, [(cam, out)], None, None))
    assert set(dc.hot_sample.tolist()) == {0.0, 1.0}
    assert abs((dc.hot_sample == 1.0).float().mean().item() - 0.75) < 0.03  # 3 / (1 + 3), 4000 draws
    torch.testing.assert_close(dc.grad_time / dc.grad_sum, torch.full((n,), 0.75))  # the mean rule's
    _set(params, optimizer, "log_scale", torch.full((n, 3), math.log(0.005)))
    sample = dc.hot_sample.clone()
    dc.densify_and_prune(params, optimizer, step=600)
    assert dc.log[-1]["cloned"] == n
    torch.testing.assert_close(params["t_center"].detach()[n:].reshape(-1), sample)


@pytest.mark.parametrize("rule", ["random", "parent"])
def test_the_other_rules_for_new_temporal_centres(rule):
    params, optimizer, _ = _setup(n=8, extent=1.0)
    dc = DensityControl(Schedule(), 1.0, Thresholds(new_t_center=rule))
    _set(params, optimizer, "log_scale", torch.full((8, 3), math.log(0.005)))
    _set(params, optimizer, "t_center", torch.full((8, 1), 0.5))
    dc._fit(8)
    _hot_at(dc, slice(None), times=[0.1], norms=[10 * dc.thresholds.grad])
    torch.manual_seed(0)
    dc.densify_and_prune(params, optimizer, step=600)
    t_new = params["t_center"].detach()[8:].reshape(-1)
    assert t_new.shape == (8,)
    if rule == "parent":
        assert torch.all(t_new == 0.5)
    else:  # the reference's: uniform in [0, 1), unrelated to the hot time 0.1
        assert torch.all((t_new >= 0) & (t_new < 1)) and len(set(t_new.tolist())) == 8


def test_a_checkpoint_without_hot_times_passes_the_parents_centres_on():
    params, optimizer, dc = _setup(n=3, extent=1.0)
    _set(params, optimizer, "log_scale", torch.full((3, 3), math.log(0.005)))
    _set(params, optimizer, "t_center", torch.tensor([[0.2], [0.4], [0.6]]))
    dc._fit(3)
    _hot_at(dc, slice(None), times=[0.9], norms=[10 * dc.thresholds.grad])
    state = dc.state_dict()
    del state["grad_time"], state["hot_sample"]
    dc.load_state_dict(state)
    dc.densify_and_prune(params, optimizer, step=600)
    torch.testing.assert_close(params["t_center"].detach()[3:].reshape(-1), torch.tensor([0.2, 0.4, 0.6]))


def test_an_unknown_rule_for_new_temporal_centres_is_refused():
    with pytest.raises(ValueError, match="new_t_center must be one of"):
        Thresholds(new_t_center="middle")
