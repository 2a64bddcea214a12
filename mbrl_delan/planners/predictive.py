"""Predictive sampling: keep the best of the nominal plan and N - 1 noisy copies of it."""

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
)
from mbrl_delan.planners.spline import INTERPOLATIONS
from mbrl_delan.rules import rule


@dataclass
class PredictiveSettings(SamplingSettings):
    """`SamplingSettings` (few samples, one iteration, three cubic knots) and noise_std, the
    perturbations' std (a scalar or (nu,); None: a quarter of the action range)."""

    num_samples: int = rule(10, low=1)
    iterations: int = rule(1, low=1)
    knots: int | None = rule(3, low=1)
    interpolation: str = rule("cubic", choices=INTERPOLATIONS)
    noise_std: float | None = rule(0.5, low=0, above=True)


@dataclass
class PredictiveConfig(PredictiveSettings, PlannerConfig):
    """``planner=predictive``: predictive sampling's settings and the loop's."""


@register_sampling_planner("predictive", PredictiveConfig)
class PredictiveSampling(SamplingPlanner):
    """Predictive sampling: each iteration evaluates the nominal knots and N - 1 copies
    perturbed by Gaussian noise of a fixed std, and the best of them becomes the nominal.
    Greedy and derivative-free; with few knots (`knots`), few samples suffice
    (`PredictiveSettings`; constructed as `SamplingPlanner`)."""

    Settings = PredictiveSettings
    STD_FIELD = "noise_std"

    def _initial_distribution(self, mean: Tensor) -> SamplingDistribution:
        std = self.init_std.to(mean.device, mean.dtype).expand_as(mean).clone()
        return SamplingDistribution(mean=mean, std=std)

    def _sample(self, dist: SamplingDistribution, generator: torch.Generator | None) -> Tensor:
        """The nominal first, then N - 1 perturbed copies. (N, K, nu)"""
        noisy = dist.mean + dist.std * self._noise(dist, generator, self.num_samples - 1)
        return torch.cat([dist.mean.unsqueeze(0), noisy], dim=0)

    def _update(
        self, dist: SamplingDistribution, samples: Tensor, returns: Tensor
    ) -> SamplingDistribution:
        return SamplingDistribution(mean=samples[torch.argmax(returns)], std=dist.std)
