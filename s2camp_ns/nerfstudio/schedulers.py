"""nerfstudio's exponential-decay scheduler with plain-float learning rates, so checkpoints load under torch >= 2.6.

nerfstudio 1.1.5 computes the learning-rate multiplier with numpy, so the optimizer and scheduler state hold
numpy.float64 values; torch.load's default weights_only=True (torch >= 2.6) then refuses the checkpoint, which
breaks resuming (--load-dir) and ns-eval / ns-viewer / ns-render. The schedule itself is unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from nerfstudio.engine.schedulers import ExponentialDecayScheduler, ExponentialDecaySchedulerConfig
from torch.optim import Optimizer, lr_scheduler


@dataclass
class FloatExponentialDecaySchedulerConfig(ExponentialDecaySchedulerConfig):
    """Exponential decay with warm-up (nerfstudio's), storing learning rates as Python floats."""

    _target: type = field(default_factory=lambda: FloatExponentialDecayScheduler)


class FloatExponentialDecayScheduler(ExponentialDecayScheduler):
    """nerfstudio's ExponentialDecayScheduler whose multipliers are cast to float."""

    def get_scheduler(self, optimizer: Optimizer, lr_init: float) -> lr_scheduler.LRScheduler:
        scheduler = super().get_scheduler(optimizer, lr_init)
        assert isinstance(scheduler, lr_scheduler.LambdaLR)
        scheduler.lr_lambdas = [lambda step, f=f: float(f(step)) for f in scheduler.lr_lambdas]
        # LambdaLR already evaluated the numpy multiplier once while it was built.
        for group in optimizer.param_groups:
            group["lr"] = float(group["lr"])
        scheduler._last_lr = [float(lr) for lr in scheduler.get_last_lr()]
        return scheduler
