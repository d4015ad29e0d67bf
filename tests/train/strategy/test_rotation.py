"""stg_train.strategy.rotation: the reference's separation of rotating from moving Gaussians."""
from __future__ import annotations

import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from stg_train.params import LearningRates, STGParams  # noqa: E402
from stg_train.strategy import Schedule, SeparateRotation, StepContext  # noqa: E402
from stg_train.strategy.ops import set_values  # noqa: E402


def _setup(n=4):
    rng = np.random.default_rng(0)
    params = STGParams.from_points(rng.normal(size=(n, 3)) + [0, 0, 4], rng.uniform(0.1, 0.9, (n, 3)),
                                   rng.uniform(0, 1, n), "lite", seed=0)
    optimizer = torch.optim.Adam(params.param_groups(LearningRates(), 1.0), eps=1e-15)
    # Gaussian 0 moves, is mid-sized and opaque: it keeps omega; 1 is at rest, 2 too small, 3 too faint
    motion = torch.zeros(n, 9)
    motion[[0, 2, 3], 0] = 0.5
    set_values(params, optimizer, "motion", motion)
    set_values(params, optimizer, "log_scale", torch.tensor([[math.log(0.3)] * 3, [math.log(0.3)] * 3,
                                                             [math.log(0.05)] * 3, [math.log(0.3)] * 3]))
    set_values(params, optimizer, "opacity_logit", torch.tensor([[3.0], [3.0], [3.0], [-3.0]]))
    set_values(params, optimizer, "omega", torch.full((n, 4), 0.1))
    return params, optimizer


def _step(params, optimizer, strategy, step):
    """One optimisation step in which every omega and rotation entry has gradient 1."""
    (params["omega"].sum() + params["rotation"].sum()).backward()
    strategy.step_post_backward(params, optimizer, step, StepContext(None, 0, 0.0, [], None, None))
    optimizer.step()
    optimizer.zero_grad(set_to_none=True)


def test_omega_is_kept_for_moving_gaussians_only_and_the_others_are_frozen():
    params, optimizer = _setup()
    strategy = SeparateRotation(Schedule(separate_at=3))
    for step in (1, 2):  # before the separation everything trains
        _step(params, optimizer, strategy, step)
    assert strategy.kept is None and torch.all(params["omega"].detach() < 0.1)
    _step(params, optimizer, strategy, 3)
    omega, rotation = params["omega"].detach().clone(), params["rotation"].detach().clone()
    assert strategy.kept == 1
    assert torch.all(omega[1:] == 0) and torch.all(omega[0] != 0)
    for step in (4, 5, 6):
        _step(params, optimizer, strategy, step)
    after_omega, after_rotation = params["omega"].detach(), params["rotation"].detach()
    assert torch.all(after_omega[1:] == 0)  # frozen at 0
    assert torch.all(after_omega[0] < omega[0])  # the mover's omega still trains
    assert torch.equal(after_rotation[0], rotation[0])  # ... and its rotation at the centre is frozen
    assert torch.all(after_rotation[1:] < rotation[1:])  # the others' rotations still train
