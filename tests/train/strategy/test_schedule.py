"""stg_train.strategy.schedule: the reference schedule stretched to a run's length."""
from __future__ import annotations

import pytest

from stg_train.strategy.schedule import Schedule


def test_a_30k_run_gets_the_reference_schedule():
    assert Schedule.scaled(30000) == Schedule()


@pytest.mark.parametrize("total", [40, 100, 150, 300, 600, 1500, 3000, 10000])
def test_no_gaussians_are_added_in_the_last_two_thirds(total):
    s = Schedule.scaled(total)
    densify_steps = [k for k in range(s.refine_start + 1, total + 1) if k % s.refine_every == 0][:s.densify_rounds]
    assert all(k <= total // 3 for k in densify_steps)
    assert s.guided_start <= total // 3 or s.guided_start > total
    if total >= 3000:  # long enough for the reference's six rounds and guided sampling
        assert len(densify_steps) == 6 and s.guided_start <= total // 3


def test_overrides_are_kept_as_given():
    s = Schedule.scaled(20, refine_start=2, refine_every=2, densify_rounds=3, guided_start=15)
    assert (s.refine_start, s.refine_every, s.densify_rounds, s.guided_start) == (2, 2, 3, 15)
    # the cap follows the overridden refine period: 20 // 3 = 6 leaves rounds at 4 and 6
    assert Schedule.scaled(20, refine_start=2, refine_every=2).densify_rounds == 2
