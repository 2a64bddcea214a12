"""The identification recipe's learning-rate schedule: stages of falling lr after a warm-up.

Stage k trains at ``lr * decay^k`` and may run an equal share of the epochs left; it ends
early when its fit stops on the validation error (`patience`), and the next stage starts from
the best weights of the one before. The first stage ramps the learning rate up linearly over
``warmup_steps`` optimizer steps: at a full 1e-2 from the first step, DeLaN's M collapses to 0
(softplus of diag L saturates) before gravity is learned. Used by ``python -m mbrl_delan.fit``
(``lr_schedule=stages``, the default for ``data=arrays``) and by the benchmark suite
``identify``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch
from torch.utils.hooks import RemovableHandle

# (stage from 0, most epochs it may run) -> epochs it ran
StageFit = Callable[[int, int], int]


@dataclass(frozen=True)
class LearningRateStages:
    """Stages of falling learning rate.

    lr: the first stage's learning rate; stage k uses lr * decay^k.
    stages: number of stages; each may run an equal share of the epochs left.
    decay: factor on the learning rate from one stage to the next.
    warmup_steps: the first stage ramps lr linearly from lr / warmup_steps over this many
        optimizer steps.
    max_epochs: epochs over all stages together.
    """

    lr: float = 1e-2
    stages: int = 4
    decay: float = 0.3
    warmup_steps: int = 200
    max_epochs: int = 500

    def __post_init__(self) -> None:
        if not self.lr > 0 or not 0 < self.decay <= 1:
            raise ValueError(f"need lr > 0 and decay in (0, 1]: {self}")
        if self.stages < 1 or self.max_epochs < 1 or self.warmup_steps < 0:
            raise ValueError(f"need stages, max_epochs >= 1 and warmup_steps >= 0: {self}")

    def stage_lr(self, stage: int) -> float:
        return self.lr * self.decay**stage


def run_stages(
    optimizer: torch.optim.Optimizer, schedule: LearningRateStages, fit_stage: StageFit
) -> int:
    """Run `fit_stage` once per stage with that stage's learning rate set in `optimizer`.

    `fit_stage(stage, epochs)` trains for at most `epochs` epochs (restoring its best
    weights) and returns how many it ran. The total number of epochs run."""
    warmup = linear_warmup(optimizer, schedule.lr, schedule.warmup_steps)
    remaining = schedule.max_epochs
    try:
        for stage in range(schedule.stages):
            if stage > 0:
                warmup.remove()
                for group in optimizer.param_groups:
                    group["lr"] = schedule.stage_lr(stage)
            share = math.ceil(remaining / (schedule.stages - stage))
            if share <= 0:
                break
            remaining -= fit_stage(stage, share)
    finally:
        warmup.remove()
    return schedule.max_epochs - remaining


def linear_warmup(optimizer: torch.optim.Optimizer, lr: float, steps: int) -> RemovableHandle:
    """Sets the learning rate to lr * min(1, (k + 1) / steps) before optimizer step k.

    Early in a DeLaN fit, before g is learned, the torque is best explained by a small M (the
    regression of tau on qdd alone); Adam's first steps at full lr overshoot into softplus's
    flat region, where diag(L) and its gradient vanish and the fit never recovers.
    """
    steps = max(steps, 1)
    taken = 0

    def set_lr(*_: Any) -> None:
        nonlocal taken
        taken += 1
        for group in optimizer.param_groups:
            group["lr"] = lr * min(1.0, (taken + 1) / steps)

    for group in optimizer.param_groups:
        group["lr"] = lr / steps
    return optimizer.register_step_post_hook(set_lr)
