"""stg_train.strategy.ops: every edit of the Gaussians keeps each parameter's Adam state in step, so that
Adam goes on as if the edited set had always been there."""
from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from stg_train.params import LearningRates, STGParams  # noqa: E402
from stg_train.strategy.ops import append_gaussians, keep_gaussians, set_values  # noqa: E402


def _params(n, seed=0, kind="full"):
    rng = np.random.default_rng(seed)
    return STGParams.from_points(rng.normal(size=(n, 3)) + [0, 0, 4], rng.uniform(0.1, 0.9, (n, 3)),
                                 rng.uniform(0, 1, n), kind, seed=seed)


def _adam(params):
    return torch.optim.Adam(params.param_groups(LearningRates(), 1.0), eps=1e-15)


def _step(params, optimizer, rows=None):
    """One Adam step on a loss that is a sum of per-Gaussian terms (of `rows` only, when given)."""
    loss = 0.0
    for name, value in params.raw.items():
        if value.requires_grad:
            part = value if rows is None else value[rows]
            loss = loss + (torch.sin(3 * part) * part).sum()
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    optimizer.step()


def _rows(params, index):
    return {name: value.detach()[index].clone() for name, value in params.raw.items()}


def _assert_same(a: STGParams, b: STGParams):
    assert a.count == b.count
    for name in a.raw:
        torch.testing.assert_close(a.raw[name], b.raw[name], rtol=0, atol=1e-7, msg=name)


def _state(optimizer, tensor):
    return optimizer.state[tensor]


def test_appended_gaussians_continue_like_ones_that_were_always_there():
    """Gaussians that never had a gradient have zero Adam moments: appending them with zero moments
    after two steps gives the same third step as having them from the start."""
    n, k = 30, 7
    always = _params(n + k)
    a_opt = _adam(always)
    late = STGParams({name: v.detach()[:n] for name, v in always.raw.items()}, "full", decoder=always.decoder)
    b_opt = _adam(late)
    for _ in range(2):
        _step(always, a_opt, rows=slice(0, n))
        _step(late, b_opt)
    append_gaussians(late, b_opt, _rows(always, slice(n, n + k)))
    for group in b_opt.param_groups:  # the optimizer holds the new tensors, with their state
        if group["name"] in late.raw:
            assert group["params"][0] is late.raw[group["name"]]
            state = _state(b_opt, late.raw[group["name"]])
            assert state["exp_avg"].shape == late.raw[group["name"]].shape
            assert torch.count_nonzero(state["exp_avg"][n:]) == 0 and torch.count_nonzero(state["exp_avg_sq"][n:]) == 0
    assert len(b_opt.state) == len(a_opt.state)  # no state left behind for the replaced tensors
    _step(always, a_opt)
    _step(late, b_opt)
    _assert_same(always, late)


def test_kept_gaussians_continue_as_if_the_others_never_existed():
    n, keep = 40, np.arange(40) % 3 != 0
    whole = _params(n, seed=1)
    w_opt = _adam(whole)
    part = STGParams({name: v.detach()[keep] for name, v in whole.raw.items()}, "full", decoder=whole.decoder)
    p_opt = _adam(part)
    for _ in range(3):  # per-Gaussian terms: the kept rows get the same gradients in both
        _step(whole, w_opt)
        _step(part, p_opt)
    keep_gaussians(whole, w_opt, torch.as_tensor(keep))
    assert whole.count == int(keep.sum())
    for name, value in whole.raw.items():
        if value.requires_grad:
            torch.testing.assert_close(_state(w_opt, value)["exp_avg"], _state(p_opt, part.raw[name])["exp_avg"])
    _step(whole, w_opt)
    _step(part, p_opt)
    _assert_same(whole, part)


def test_set_values_zeroes_the_moments_of_that_parameter_only():
    params = _params(12, seed=2)
    opt = _adam(params)
    _step(params, opt)
    new = torch.full_like(params["opacity_logit"], -4.0)
    before = _state(opt, params["xyz"])["exp_avg"].clone()
    set_values(params, opt, "opacity_logit", new)
    torch.testing.assert_close(params["opacity_logit"].detach(), new)
    state = _state(opt, params["opacity_logit"])
    assert torch.count_nonzero(state["exp_avg"]) == 0 and torch.count_nonzero(state["exp_avg_sq"]) == 0
    torch.testing.assert_close(_state(opt, params["xyz"])["exp_avg"], before)
    assert params["opacity_logit"].requires_grad and params["opacity_logit"].is_leaf


def test_frozen_parameters_are_edited_without_optimizer_state():
    params = STGParams.from_points(np.random.default_rng(3).normal(size=(10, 3)), np.full((10, 3), 0.5),
                                   np.zeros(10), "lite", static=True)
    opt = _adam(params)
    _step(params, opt)
    append_gaussians(params, opt, _rows(params, slice(0, 4)))
    keep_gaussians(params, opt, torch.arange(14) % 2 == 0)
    assert params.count == 7
    assert not params["motion"].requires_grad and params["motion"] not in opt.state
    assert all(t.shape[0] == 7 for t in params.raw.values())
