"""Model predictive path integral control as a batched functional optimiser."""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor

from mbrl_delan.planners.base import SamplingDistribution, SamplingPlanner, require


def mppi_weights(returns: Tensor, temperature: float) -> Tensor:
    """Softmax weights exp((R - max R) / temperature), finite for any returns. (N,) -> (N,)

    Returns of -inf (or NaN, mapped to -inf before) get weight 0; when no return is finite
    the weights are uniform.
    """
    finite = torch.isfinite(returns)
    best = torch.where(finite, returns, -math.inf).max()
    logits = torch.where(finite, (returns - best) / temperature, -math.inf)
    logits = torch.where(finite.any(), logits, torch.zeros_like(logits))
    return torch.softmax(logits, dim=0)


class MPPIPlanner(SamplingPlanner):
    """MPPI: perturb the mean with fixed Gaussian noise, average samples by exp(R / lambda).

    Args (beyond `SamplingPlanner`'s):
        temperature: lambda > 0; small values approach picking the best sample.
        noise_std: standard deviation of the perturbations, scalar or (nu,), > 0. None
            falls back to `init_std`.
    """

    def __init__(
        self,
        horizon: int,
        action_low: Tensor | Sequence[float] | float,
        action_high: Tensor | Sequence[float] | float,
        num_samples: int = 512,
        iterations: int = 1,
        temperature: float = 1.0,
        noise_std: float | Sequence[float] | None = None,
        shift_fill: str = "repeat",
        dtype: torch.dtype = torch.float32,
    ) -> None:
        require(
            math.isfinite(temperature) and temperature > 0,
            f"temperature must be finite and > 0, got {temperature}",
        )
        super().__init__(
            horizon,
            action_low,
            action_high,
            num_samples,
            iterations,
            init_std=noise_std,
            shift_fill=shift_fill,
            dtype=dtype,
        )
        self.temperature = temperature

    @property
    def noise_std(self) -> Tensor:
        """(nu,) float64."""
        return self.init_std

    def _initial_distribution(self, mean: Tensor) -> SamplingDistribution:
        std = self.init_std.to(mean.device, mean.dtype).expand_as(mean).clone()
        return SamplingDistribution(mean=mean, std=std)

    def _update(
        self, dist: SamplingDistribution, samples: Tensor, returns: Tensor
    ) -> SamplingDistribution:
        weights = mppi_weights(returns, self.temperature).to(samples.dtype)  # (N,)
        mean = torch.einsum("n,nhu->hu", weights, samples)
        return SamplingDistribution(mean=mean, std=dist.std)
