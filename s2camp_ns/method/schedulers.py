"""The camera's learning-rate schedule, which follows the run's length.

``RunLengthScheduleConfig`` states CamP's camera schedule (warm-up over 2.5k of 30k steps, decay to a tenth by 25k) as
fractions of the run, so any run length gets it stretched or compressed, except that the warm-up never drops below
``min_warmup_steps``: the field converges in its own number of steps, and a camera that moves before the field fits
follows the field's errors. ``S2CampTrainer`` fills in the run length. The schedule itself is nerfstudio's
exponential decay with warm-up, whose numpy rates ``S2CampTrainer`` stores as Python floats in checkpoints.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from nerfstudio.engine.schedulers import (
    ExponentialDecayScheduler,
    ExponentialDecaySchedulerConfig,
    Scheduler,
    SchedulerConfig,
)
from torch.optim import Optimizer, lr_scheduler

from s2camp_ns.core.validation import check_positive_int, check_range


@dataclass
class RunLengthScheduleConfig(SchedulerConfig):
    """Cosine warm-up from ``lr_pre_warmup`` to the optimizer's lr over ``warmup_fraction`` of the run (at least
    ``min_warmup_steps``), then exponential decay to ``lr_final``, constant after. The decay takes its share
    (decay_end_fraction - warmup_fraction) / (1 - warmup_fraction) of the steps after the warm-up, at least one.
    ``warmup_steps`` / ``max_steps`` (nerfstudio's meaning) replace the fractions by step counts.
    """

    _target: type = field(default_factory=lambda: RunLengthSchedule)
    lr_pre_warmup: float = 1e-8
    """Learning rate at step 0."""
    lr_final: float = 1e-5
    """Learning rate at the end of the decay."""
    warmup_fraction: float = 2500 / 30000
    """Fraction of the run spent warming up (at least ``min_warmup_steps``)."""
    min_warmup_steps: int = 2500
    """Fewest warm-up steps, whatever the run length."""
    decay_end_fraction: float = 25000 / 30000
    """Fraction of the run at which the decay reaches ``lr_final`` (unfloored warm-up); > ``warmup_fraction``."""
    warmup_steps: int | None = None
    """Warm-up steps; None: ``warmup_fraction`` of the run, at least ``min_warmup_steps``."""
    max_steps: int | None = None
    """Step at which the decay ends; None: from ``decay_end_fraction``."""
    run_steps: int | None = None
    """Steps of the run; None: ``--max-num-iterations``, filled in by ``S2CampTrainer``."""

    def step_counts(self) -> tuple[int, int]:
        """(warm-up steps, step at which the decay ends); ValueError naming a parameter out of range."""
        check_range("warmup_fraction", self.warmup_fraction, low=0.0, high=1.0, high_inclusive=False)
        check_range("decay_end_fraction", self.decay_end_fraction, low=0.0, high=1.0, low_inclusive=False)
        check_range("lr_pre_warmup", self.lr_pre_warmup, low=0.0, low_inclusive=False)
        check_range("lr_final", self.lr_final, low=0.0, low_inclusive=False)
        if self.warmup_steps is None or self.max_steps is None:
            if self.run_steps is None:
                raise ValueError(
                    "run_steps is None: the run length was not filled in (S2CampTrainer does it from "
                    "--max-num-iterations); set run_steps, or warmup_steps and max_steps, to positive integers"
                )
            check_positive_int("run_steps", self.run_steps)
        if self.warmup_steps is None:
            assert self.run_steps is not None
            check_range("min_warmup_steps", self.min_warmup_steps, low=0)
            warmup = max(round(self.warmup_fraction * self.run_steps), self.min_warmup_steps)
        else:
            check_range("warmup_steps", self.warmup_steps, low=0)
            warmup = self.warmup_steps
        if self.max_steps is None:
            assert self.run_steps is not None
            check_range("decay_end_fraction", self.decay_end_fraction, low=self.warmup_fraction, low_inclusive=False)
            decay_share = (self.decay_end_fraction - self.warmup_fraction) / (1.0 - self.warmup_fraction)
            end = warmup + max(round(decay_share * (self.run_steps - warmup)), 1)
        else:
            check_range("max_steps", self.max_steps, low=warmup, low_inclusive=False)
            end = self.max_steps
        return warmup, end


class RunLengthSchedule(Scheduler):
    """The schedule of ``RunLengthScheduleConfig``: nerfstudio's exponential decay with step counts from the run."""

    config: RunLengthScheduleConfig

    def get_scheduler(self, optimizer: Optimizer, lr_init: float) -> lr_scheduler.LRScheduler:
        warmup_steps, max_steps = self.config.step_counts()
        steps = ExponentialDecaySchedulerConfig(
            lr_pre_warmup=self.config.lr_pre_warmup,
            lr_final=self.config.lr_final,
            warmup_steps=warmup_steps,
            max_steps=max_steps,
        )
        return ExponentialDecayScheduler(steps).get_scheduler(optimizer, lr_init)
