"""Cross-entropy method (PETS / mbrl-lib style) as a batched functional optimiser."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from mbrl_delan.planners.base import (
    PlannerConfig,
    SamplingDistribution,
    SamplingPlanner,
    SamplingSettings,
    register_sampling_planner,
    require,
)
from mbrl_delan.rules import rule


@dataclass
class CEMSettings(SamplingSettings):
    """`SamplingSettings` and CEM's own: num_elites K best samples the distribution is refit
    to (1 <= K <= num_samples); init_std the first iteration's std (a scalar or (nu,); None:
    a quarter of the action range); min_std the floor on the std after each update; momentum
    alpha in mean = alpha * mean + (1 - alpha) * elite_mean (same for std), 0 <= alpha < 1."""

    num_elites: int = rule(25, low=1)
    init_std: float | None = rule(0.5, low=0, above=True)
    min_std: float = rule(0.05, low=0)
    momentum: float = rule(0.1, low=0, high=1, below=True)


def check_cem(settings: CEMSettings) -> None:
    """The rules between CEM's settings, beyond their ranges."""
    s = settings
    require(
        1 <= s.num_elites <= s.num_samples,
        f"num_elites must be in [1, num_samples={s.num_samples}], got {s.num_elites}",
    )
    require(s.min_std >= 0, f"min_std must be >= 0, got {s.min_std}")
    require(0 <= s.momentum < 1, f"momentum must be in [0, 1), got {s.momentum}")


@dataclass
class CEMConfig(CEMSettings, PlannerConfig):
    """``planner=cem``: CEM's settings and the loop's."""


@register_sampling_planner("cem", CEMConfig)
class CEMPlanner(SamplingPlanner):
    """CEM: sample around a Gaussian, refit it to the top `num_elites`, repeat
    (`CEMSettings`; constructed as `SamplingPlanner`)."""

    Settings = CEMSettings

    def _take(self, settings: CEMSettings) -> None:
        check_cem(settings)
        self.num_elites = settings.num_elites
        self.min_std = settings.min_std
        self.momentum = settings.momentum

    def _initial_distribution(self, mean: Tensor) -> SamplingDistribution:
        std = self.init_std.to(mean.device, mean.dtype).expand_as(mean).clone()
        return SamplingDistribution(mean=mean, std=std)

    def _update(
        self, dist: SamplingDistribution, samples: Tensor, returns: Tensor
    ) -> SamplingDistribution:
        elite_idx = torch.topk(returns, self.num_elites, sorted=False).indices  # (K,)
        elites = samples[elite_idx]  # (K, H, nu)
        elite_mean = elites.mean(dim=0)
        elite_std = elites.std(dim=0, correction=0)
        a = self.momentum
        mean = a * dist.mean + (1 - a) * elite_mean
        std = (a * dist.std + (1 - a) * elite_std).clamp_min(self.min_std)
        return SamplingDistribution(mean=mean, std=std)
