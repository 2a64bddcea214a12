"""Predictive sampling: keep the best of the nominal plan and N - 1 noisy copies of it."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from mbrl_delan.planners.base import SamplingDistribution, SamplingPlanner


class PredictiveSampling(SamplingPlanner):
    """Predictive sampling: each iteration evaluates the nominal knots and N - 1 copies
    perturbed by Gaussian noise of a fixed std, and the best of them becomes the nominal.
    Greedy and derivative-free; with few knots (`knots`), few samples suffice.

    Args (beyond `SamplingPlanner`'s):
        noise_std: standard deviation of the perturbations, scalar or (nu,), > 0. None
            falls back to a quarter of the action range (`init_std`).
    """

    def __init__(
        self,
        horizon: int,
        action_low: Tensor | Sequence[float] | float,
        action_high: Tensor | Sequence[float] | float,
        num_samples: int = 10,
        iterations: int = 1,
        noise_std: float | Sequence[float] | None = None,
        shift_fill: str = "repeat",
        dtype: torch.dtype = torch.float32,
        knots: int | None = None,
        interpolation: str = "linear",
    ) -> None:
        super().__init__(
            horizon,
            action_low,
            action_high,
            num_samples,
            iterations,
            init_std=noise_std,
            shift_fill=shift_fill,
            dtype=dtype,
            knots=knots,
            interpolation=interpolation,
        )

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
