"""The strategies a run uses, by name, in the order they act: the one place a strategy is registered.

The trainer calls build_strategies(StrategySetup(...)) once per run (fresh or resumed) and steps the
list it returns; a checkpoint keeps each one's state_dict() in that order. Each entry of STRATEGIES
makes its strategy from the run's settings, or returns None where the run turns it off (TrainConfig's
switches). A new strategy is one module in this package and one entry here (docs/extending.md).
"""
from __future__ import annotations

from typing import Callable, NamedTuple

import numpy as np

from .base import Strategy
from .density import DensityControl, Thresholds
from .guided import GuidedSampling, GuidedSettings
from .rotation import SeparateRotation
from .schedule import Schedule


class StrategySetup(NamedTuple):
    """What a strategy is made from: config, the run's TrainConfig; schedule, its Schedule scaled to the
    run's steps; extent, the training cameras' extent (world units, params.extent_of); box, (2, 3) the
    initial points' bounding box (min, max), world units."""

    config: object
    schedule: Schedule
    extent: float
    box: np.ndarray


def _density(setup: StrategySetup) -> Strategy:
    return DensityControl(setup.schedule, setup.extent, Thresholds(**setup.config.thresholds), box=setup.box)


def _guided(setup: StrategySetup) -> Strategy | None:
    return GuidedSampling(setup.schedule, GuidedSettings(**setup.config.guided_settings)) if setup.config.guided else None


def _rotation(setup: StrategySetup) -> Strategy | None:
    return SeparateRotation(setup.schedule) if setup.config.separate_rotation else None


#: name -> make(setup) -> Strategy or None (off for this run). DensityControl comes first: the others
#: append Gaussians, whose statistics it extends.
STRATEGIES: dict[str, Callable[[StrategySetup], Strategy | None]] = {
    "density": _density,
    "guided": _guided,
    "rotation": _rotation,
}


def build_strategies(setup: StrategySetup) -> list[Strategy]:
    """The run's strategies, in STRATEGIES' order, those turned off left out."""
    made = (make(setup) for make in STRATEGIES.values())
    return [strategy for strategy in made if strategy is not None]
