"""Cross-entropy method (PETS / mbrl-lib style) as a batched functional optimiser."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from mbrl_delan.planners.base import SamplingDistribution, SamplingPlanner, require


class CEMPlanner(SamplingPlanner):
    """CEM: sample around a Gaussian, refit it to the top `num_elites`, repeat.

    Args (beyond `SamplingPlanner`'s):
        num_elites: K best samples the distribution is refit to (1 <= K <= num_samples).
        min_std: floor on the standard deviation after each update (>= 0).
        momentum: alpha in mean = alpha * mean + (1 - alpha) * elite_mean (same for std),
            0 <= alpha < 1.
    """

    def __init__(
        self,
        horizon: int,
        action_low: Tensor | Sequence[float] | float,
        action_high: Tensor | Sequence[float] | float,
        num_samples: int = 500,
        num_elites: int = 50,
        iterations: int = 5,
        init_std: float | Sequence[float] | None = None,
        min_std: float = 1e-3,
        momentum: float = 0.1,
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
            init_std=init_std,
            shift_fill=shift_fill,
            dtype=dtype,
            knots=knots,
            interpolation=interpolation,
        )
        require(
            1 <= num_elites <= num_samples,
            f"num_elites must be in [1, num_samples={num_samples}], got {num_elites}",
        )
        require(min_std >= 0, f"min_std must be >= 0, got {min_std}")
        require(0 <= momentum < 1, f"momentum must be in [0, 1), got {momentum}")
        self.num_elites = num_elites
        self.min_std = min_std
        self.momentum = momentum

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
