"""Model predictive path integral control as a batched functional optimiser."""

from __future__ import annotations

import math
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


def ar1_filter(horizon: int, smoothing: float, dtype: torch.dtype, device: torch.device) -> Tensor:
    """Matrix F (H, H) with eps = F n an AR(1) series of unit variance from white noise n.

    eps_0 = n_0 and eps_t = a eps_{t-1} + sqrt(1 - a^2) n_t with a = `smoothing`, so every
    eps_t is N(0, 1) and Corr(eps_t, eps_s) = a^|t - s|: F[t, 0] = a^t and
    F[t, s] = sqrt(1 - a^2) a^(t - s) for 1 <= s <= t. a = 0 gives the identity.
    """
    t = torch.arange(horizon, dtype=torch.float64)
    lag = t[:, None] - t[None, :]  # (H, H) t - s
    gain = torch.full((horizon,), math.sqrt(1.0 - smoothing**2), dtype=torch.float64)
    gain[0] = 1.0
    a = torch.tensor(smoothing, dtype=torch.float64)
    powers = torch.where(lag >= 0, a ** lag.clamp_min(0), 0.0)  # a^(t - s), zero above
    return (powers * gain[None, :]).to(device=device, dtype=dtype)


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


@dataclass
class MPPISettings(SamplingSettings):
    """`SamplingSettings` (MPPI's sample count and iterations) and MPPI's own: temperature
    lambda > 0 (small values approach picking the best sample); noise_std the perturbations'
    std (a scalar or (nu,); None: a quarter of the action range); smoothing a in [0, 1): the
    perturbations are an AR(1) series along the horizon, eps_t = a eps_{t-1} +
    sqrt(1 - a^2) n_t (`ar1_filter`), so neighbouring actions move together while each keeps
    the std `noise_std`; 0 is white noise."""

    num_samples: int = rule(256, low=1)
    iterations: int = rule(2, low=1)
    temperature: float = rule(0.5, low=0, above=True)
    noise_std: float | None = rule(0.5, low=0, above=True)
    smoothing: float = rule(0.8, low=0, high=1, below=True)


@dataclass
class MPPIConfig(MPPISettings, PlannerConfig):
    """``planner=mppi``: MPPI's settings and the loop's."""


@register_sampling_planner("mppi", MPPIConfig)
class MPPIPlanner(SamplingPlanner):
    """MPPI: perturb the mean with fixed Gaussian noise, average samples by exp(R / lambda)
    (`MPPISettings`; constructed as `SamplingPlanner`)."""

    Settings = MPPISettings
    STD_FIELD = "noise_std"

    def _take(self, settings: MPPISettings) -> None:
        temperature, smoothing = settings.temperature, settings.smoothing
        require(
            math.isfinite(temperature) and temperature > 0,
            f"temperature must be finite and > 0, got {temperature}",
        )
        require(0 <= smoothing < 1, f"smoothing must be in [0, 1), got {smoothing}")
        self.temperature = temperature
        self.smoothing = float(smoothing)
        self._filters: dict[tuple[torch.device, torch.dtype], Tensor] = {}

    @property
    def noise_std(self) -> Tensor:
        """(nu,) float64."""
        return self.init_std

    def _initial_distribution(self, mean: Tensor) -> SamplingDistribution:
        std = self.init_std.to(mean.device, mean.dtype).expand_as(mean).clone()
        return SamplingDistribution(mean=mean, std=std)

    def _noise(
        self, dist: SamplingDistribution, generator: torch.Generator | None, num: int
    ) -> Tensor:
        """Unit-variance noise (num, K, nu): white, or AR(1) along the knots with `smoothing`."""
        white = super()._noise(dist, generator, num)
        if self.smoothing == 0.0:
            return white
        key = (white.device, white.dtype)
        if key not in self._filters:
            with torch.inference_mode(False):  # a normal tensor, usable in and out of it
                self._filters[key] = ar1_filter(
                    white.shape[1], self.smoothing, white.dtype, white.device
                )
        return torch.einsum("ts,nsu->ntu", self._filters[key], white)

    def _update(
        self, dist: SamplingDistribution, samples: Tensor, returns: Tensor
    ) -> SamplingDistribution:
        weights = mppi_weights(returns, self.temperature).to(samples.dtype)  # (N,)
        mean = torch.einsum("n,nhu->hu", weights, samples)
        return SamplingDistribution(mean=mean, std=dist.std)
