"""When the strategies act: the reference implementation's schedule (N3V settings, 30k iterations),
stretched to a run of any length."""
from __future__ import annotations

from dataclasses import dataclass, replace


@dataclass(frozen=True)
class Schedule:
    """When density control acts (iteration numbers of the run it is used in)."""

    refine_start: int = 500  # first densify / prune step (exclusive, as the reference: it > start)
    refine_every: int = 100
    densify_rounds: int = 6  # densification steps; later refine steps only prune
    prune_until: int = 7000
    reset_every: int = 3000  # opacity reset period; 0 disables
    reset_until: int = 9000
    outside_at: int = 10000  # remove Gaussians outside the initial box at this step; 0 disables
    guided_start: int = 1600  # guided sampling (strategy.guided): views chosen at this step, first sampling
    guided_every: int = 100  # steps between guided samplings (one per chosen view)
    separate_at: int = 8001  # strategy.rotation (when enabled): rotating and moving Gaussians separated

    @classmethod
    def scaled(cls, total: int, reference_total: int = 30000, min_every: int = 25, min_start: int = 50,
               min_reset_every: int = 1000, **overrides) -> "Schedule":
        """The reference schedule (for `reference_total` iterations) stretched to `total` iterations.

        Floors keep short runs sensible (measured on the synthetic scenes): at least `min_every` steps of
        gradient statistics per refine step, the first after `min_start` steps, and opacity resets at
        least `min_reset_every` steps apart (opacity needs that long to recover; runs shorter than
        about 3x that have none). Guided sampling starts where the reference's does relative to density
        control (its 1600 = refine_start + (densify_rounds + 5) refine periods, after the densification
        rounds, once the loss is stable), or at the scaled 1600 if later; its samplings are a refine
        period apart. Nothing is added in the last two thirds of a run, as in the reference (its last
        Gaussians come at 1700 of 30000): densification rounds and guided sampling that would start
        after `total` // 3 are dropped (unless densify_rounds or guided_start is given), so a short run
        does not end on untrained new Gaussians (a 100-step run densified at its last step lost 2.4 dB
        held-out, docs/training.md). A 30k-iteration run gets exactly the reference schedule. Keyword
        overrides replace single fields (they do not move the other fields)."""
        f = total / reference_total
        ref = cls()
        start = max(min_start, round(ref.refine_start * f))
        every = max(min_every, round(ref.refine_every * f))
        sched = cls(refine_start=start, refine_every=every,
                    densify_rounds=ref.densify_rounds,
                    prune_until=round(ref.prune_until * f),
                    reset_every=max(min_reset_every, round(ref.reset_every * f)),
                    reset_until=round(ref.reset_until * f),
                    outside_at=round(ref.outside_at * f),
                    guided_start=max(round(ref.guided_start * f), start + (ref.densify_rounds + 5) * every),
                    guided_every=max(min_every, round(ref.guided_every * f)),
                    separate_at=max(1, round(ref.separate_at * f)))
        sched = replace(sched, **overrides)
        last = total // 3  # the last step that may add Gaussians
        if "densify_rounds" not in overrides:
            first = (sched.refine_start // sched.refine_every + 1) * sched.refine_every
            fit = max(0, (last - first) // sched.refine_every + 1)
            sched = replace(sched, densify_rounds=min(sched.densify_rounds, fit))
        if "guided_start" not in overrides and sched.guided_start > last:
            sched = replace(sched, guided_start=total + 1)
        return sched
