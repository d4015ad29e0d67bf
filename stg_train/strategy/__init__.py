"""Strategies: plug-ins that edit the Gaussians around backward() (gsplat's Strategy idea).

    base       the Strategy protocol and StepContext, what a strategy sees of a step
    schedule   when they act (the reference's schedule stretched to the run)
    ops        append / keep / set Gaussians with their Adam state in step
    density    DensityControl: clone, split, prune, opacity reset
    guided     GuidedSampling: new Gaussians along the rays of high-error patches (the paper's Sec. 4.4)
    rotation   SeparateRotation: the reference's step that keeps rotation velocities for moving Gaussians
    registry   STRATEGIES, build_strategies: which a run uses, by name, in the order they act
"""
from .base import StepContext, Strategy
from .density import DensityControl, Thresholds
from .guided import GuidedSampling, GuidedSettings
from .rotation import SeparateRotation, SeparationThresholds
from .registry import STRATEGIES, StrategySetup, build_strategies
from .schedule import Schedule

__all__ = ["STRATEGIES", "DensityControl", "GuidedSampling", "GuidedSettings", "Schedule", "SeparateRotation",
           "SeparationThresholds", "StepContext", "Strategy", "StrategySetup", "Thresholds", "build_strategies"]
