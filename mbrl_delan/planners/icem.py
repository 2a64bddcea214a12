"""Improved cross-entropy method (iCEM): colored noise, kept elites, population decay.

Differences from CEM (Pinneri et al., 2020, "Sample-efficient cross-entropy method for
real-time planning"):

* samples are mean + std * colored noise, a Gaussian process along the time axis whose
  power spectrum falls as 1/f^beta (beta = 0: white noise, larger: smoother sequences),
  drawn by an inverse FFT over twice the horizon and cut to it (no wrap-around);
* a fraction of each iteration's elites is evaluated again in the next iteration, and the
  shifted elites of the previous call can seed the first iteration of the next one;
* the population shrinks by a factor `decay` per iteration, down to `min_samples`;
* optionally the best sequence seen, not the distribution mean, is the returned plan.

The iteration counter and the kept elites live in the sampling distribution and the result,
never in the planner, so one planner can serve several independent callers.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from mbrl_delan.planners.base import (
    PlannerConfig,
    PlanResult,
    PlanTrace,
    SamplingDistribution,
    SamplingPlanner,
    register_sampling_planner,
    require,
)
from mbrl_delan.planners.cem import CEMSettings, check_cem
from mbrl_delan.rules import rule


@dataclass
class ICEMDistribution(SamplingDistribution):
    """CEM's Gaussian plus what iCEM carries from one iteration to the next."""

    iteration: int  # index of the iteration this distribution samples for
    kept: Tensor  # (n_keep, H, nu) elites re-evaluated in that iteration; may be (0, H, nu)


@dataclass
class ICEMPlanResult(PlanResult):
    """`PlanResult` plus iCEM's warm-start state.

    `mean` is the plan to execute: the distribution mean, or the best sequence seen when the
    planner has `return_best`; `dist_mean` is always the distribution mean.
    """

    dist_mean: Tensor  # (H, nu) final mean of the sampling distribution, within bounds
    elites: Tensor  # (n_keep, H, nu) best-first elites of the last iteration, to warm start
    population: tuple[int, ...]  # objective batch size of each iteration


def colored_noise_scales(
    length: int, beta: float, dtype: torch.dtype, device: torch.device
) -> Tensor:
    """Amplitude per rfft bin of a length-L series, f^(-beta/2) with f >= 1/L. (F,)

    Real bins (DC and, for even L, Nyquist) carry one real Gaussian where the other bins
    carry a complex one; a factor sqrt(2) on them makes beta = 0 exactly white noise.
    """
    freqs = torch.fft.rfftfreq(length, device=device, dtype=dtype)  # (F,) in [0, 1/2]
    scales = freqs.clamp_min(1.0 / length).pow(-beta / 2.0)
    real_bins = torch.zeros_like(scales, dtype=torch.bool)
    real_bins[0] = True
    if length % 2 == 0:
        real_bins[-1] = True
    return torch.where(real_bins, scales * math.sqrt(2.0), scales)


def colored_noise(
    shape: tuple[int, int, int],
    beta: float,
    generator: torch.Generator | None = None,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
    periodic: bool = False,
) -> Tensor:
    """Gaussian noise (N, H, nu) with power spectrum ~ 1/f^beta along H and unit variance.

    Each of the N * nu series is independent; at every time step each entry is N(0, 1)
    exactly (the normalisation is the closed-form variance, not an empirical one).

    A series made by one inverse FFT of length H is periodic: its last step is as strongly
    tied to its first as to its second-to-last, so a ramp from one end to the other is a
    high-frequency (rare) pattern. Unless `periodic`, the series is therefore drawn with
    length 2 H and its first H steps are kept, which leaves the 1/f^beta shape and the unit
    variance as they are and removes the wrap-around.
    """
    num, horizon, nu = shape
    device = torch.device(device) if device is not None else torch.device("cpu")
    length = horizon if periodic else 2 * horizon
    scales = colored_noise_scales(length, beta, dtype, device)  # (F,)
    bins = scales.shape[0]
    real = torch.randn((num, nu, bins), generator=generator, device=device, dtype=dtype)
    imag = torch.randn((num, nu, bins), generator=generator, device=device, dtype=dtype)
    imag[..., 0] = 0.0  # DC is real
    if length % 2 == 0:
        imag[..., -1] = 0.0  # so is Nyquist
    spectrum = torch.complex(real * scales, imag * scales)  # (N, nu, F)
    series = torch.fft.irfft(spectrum, n=length, dim=-1)[..., :horizon]  # (N, nu, H)
    # x_t = (X_0 + 2 sum_k Re(X_k e^(2 pi i k t / L)) + X_Nyq (-1)^t) / L, so
    # Var(x_t) = sum_k w_k scale_k^2 / L^2 with w = 1 on real bins and 4 on complex ones
    # (the real-bin scales already include their sqrt(2)), the same for every t
    weights = torch.full_like(scales, 4.0)
    weights[0] = 1.0
    if length % 2 == 0:
        weights[-1] = 1.0
    std = torch.sqrt((weights * scales.square()).sum()) / length
    return (series / std).transpose(1, 2)  # (N, H, nu)


@dataclass
class ICEMSettings(CEMSettings):
    """`CEMSettings` (K = num_elites <= min_samples) and iCEM's own: beta the exponent of the
    noise's power spectrum 1/f^beta along the horizon (>= 0; 0 white, 2 Brownian-like, smooth
    sequences); decay the population's decay factor per iteration (>= 1; 1 keeps it);
    min_samples the population's floor N_min, num_elites <= N_min <= num_samples (None:
    min(num_samples, 2 num_elites)); keep_elites the fraction of the elites carried into the
    next iteration, in [0, 1]; return_best: the best sequence seen is the plan (`mean`)
    instead of the distribution mean."""

    beta: float = rule(2.0, low=0)
    decay: float = rule(1.25, low=1)
    min_samples: int | None = rule(None, low=1)
    keep_elites: float = rule(0.3, low=0, high=1)
    return_best: bool = False


@dataclass
class ICEMConfig(ICEMSettings, PlannerConfig):
    """``planner=icem``: iCEM's settings and the loop's."""


@register_sampling_planner("icem", ICEMConfig)
class ICEMPlanner(SamplingPlanner):
    """iCEM: CEM with colored noise, kept elites, population decay and best-sample return.

    Iteration i evaluates N_i = max(min_samples, floor(num_samples * decay^-i)) sequences:
    the kept elites (when there are any) plus fresh samples mean + std * colored noise.
    The distribution is refit to the top `num_elites` of all N_i, with momentum and a floor
    on the std as in CEM; the best ceil(keep_elites * num_elites) elites (at least one when
    keep_elites > 0) are kept for the next iteration and returned in `ICEMPlanResult.elites`.

    Settings: `ICEMSettings` (`num_samples` is the first population N_0); constructed as
    `SamplingPlanner`.
    """

    Settings = ICEMSettings

    def _take(self, settings: ICEMSettings) -> None:
        check_cem(settings)
        s = settings
        min_samples = (
            min(s.num_samples, 2 * s.num_elites) if s.min_samples is None else s.min_samples
        )
        require(
            s.num_elites <= min_samples <= s.num_samples,
            f"min_samples must be in [num_elites={s.num_elites}, num_samples={s.num_samples}]"
            f", got {min_samples}",
        )
        require(
            math.isfinite(s.beta) and s.beta >= 0, f"beta must be finite and >= 0, got {s.beta}"
        )
        require(
            math.isfinite(s.decay) and s.decay >= 1, f"decay must be finite and >= 1, got {s.decay}"
        )
        require(0 <= s.keep_elites <= 1, f"keep_elites must be in [0, 1], got {s.keep_elites}")
        self.num_elites = s.num_elites
        self.beta = float(s.beta)
        self.decay = float(s.decay)
        self.min_samples = min_samples
        self.keep_elites = s.keep_elites
        self.num_kept = self._kept_count(s.keep_elites, s.num_elites)
        require(
            self.num_kept < min_samples,
            f"keep_elites={s.keep_elites} keeps {self.num_kept} elites, which leaves no "
            f"fresh sample in a population of min_samples={min_samples}",
        )
        self.min_std = s.min_std
        self.momentum = s.momentum
        self.return_best = s.return_best

    @staticmethod
    def _kept_count(fraction: float, num_elites: int) -> int:
        if fraction == 0:
            return 0
        return max(1, min(num_elites, math.ceil(fraction * num_elites - 1e-9)))

    def population(self, iteration: int) -> int:
        """Objective batch size N_i of iteration i (kept elites included)."""
        decayed = math.floor(self.num_samples * self.decay ** (-iteration) + 1e-9)
        return max(self.min_samples, decayed)

    def shift_elites(self, elites: Tensor, steps: int = 1) -> Tensor:
        """Warm start for kept elites: `shift` applied to each. (K, H, nu) -> (K, H, nu)"""
        require(steps >= 0, f"steps must be >= 0, got {steps}")
        expected = (self.horizon, self.action_dim)
        require(
            elites.ndim == 3 and tuple(elites.shape[1:]) == expected,
            f"elites must have shape (K, {expected[0]}, {expected[1]}), got {tuple(elites.shape)}",
        )
        kept = elites[:, min(steps, self.horizon) :]
        n_fill = self.horizon - kept.shape[1]
        if self.shift_fill == "repeat":
            fill = elites[:, -1:].expand(-1, n_fill, -1)
        else:
            fill = self.clamp(elites.new_zeros((elites.shape[0], n_fill, self.action_dim)))
        return torch.cat([kept, fill], dim=1)

    def carry(self, result: PlanResult) -> dict[str, Tensor]:
        """Keep the final elites: the next plan starts with them shifted (kept elites)."""
        elites = getattr(result, "elites", None)
        return {} if elites is None or elites.shape[0] == 0 else {"elites": elites}

    def warm_start(self, carried: dict[str, Tensor], steps: int) -> dict[str, Tensor]:
        if "elites" not in carried:
            return {}
        return {"init_elites": self.shift_elites(carried["elites"], steps)}

    # ------------------------------------------------------------------ the hooks
    def _warm_distribution(
        self, dist: ICEMDistribution, init_elites: Tensor | None = None
    ) -> ICEMDistribution:
        """Seed the first iteration with kept elites.

        `plan(..., init_elites=E)`: E (K, H, nu) are evaluated in the first iteration,
        typically `shift_elites(previous_result.elites, steps)`; at most `num_kept` of them
        are used (the first ones). None or empty: a cold first iteration.
        """
        if init_elites is not None and self.num_kept > 0:
            dist.kept = self._warm_elites(init_elites, dist.mean)
        return dist

    def _result(self, dist: ICEMDistribution, trace: PlanTrace) -> ICEMPlanResult:
        """`PlanResult` plus the distribution mean, the kept elites and the populations."""
        dist_mean = self._actions(self.clamp(dist.mean))
        return ICEMPlanResult(
            mean=trace.best_actions if self.return_best else dist_mean,
            std=self.spline.actions(dist.std),
            best_actions=trace.best_actions,
            best_return=trace.best_return,
            iteration_best=torch.stack(trace.iteration_best),
            dist_mean=dist_mean,
            elites=self._actions(dist.kept),
            population=tuple(trace.population),
        )

    def _warm_elites(self, elites: Tensor, like: Tensor) -> Tensor:
        """The knots of the first `num_kept` of the given elites (k, H, nu), checked and
        clamped. -> (k, K, nu)"""
        expected = (self.horizon, self.action_dim)
        require(
            elites.ndim == 3 and tuple(elites.shape[1:]) == expected,
            f"init_elites must have shape (K, {expected[0]}, {expected[1]}), got "
            f"{tuple(elites.shape)}",
        )
        kept = self.clamp(elites[: self.num_kept].to(like.device, like.dtype))
        return self.spline.knots_of(kept)

    def _initial_distribution(self, mean: Tensor) -> ICEMDistribution:
        std = self.init_std.to(mean.device, mean.dtype).expand_as(mean).clone()
        kept = mean.new_empty((0, *mean.shape))
        return ICEMDistribution(mean=mean, std=std, iteration=0, kept=kept)

    def _noise(
        self, dist: SamplingDistribution, generator: torch.Generator | None, num: int
    ) -> Tensor:
        """Colored noise (num, H, nu) with exponent `beta`, unit variance."""
        return colored_noise(
            (num, *dist.mean.shape),
            self.beta,
            generator,
            device=dist.mean.device,
            dtype=dist.mean.dtype,
        )

    def _sample(self, dist: ICEMDistribution, generator: torch.Generator | None) -> Tensor:
        """Kept elites followed by fresh samples, N_i in all. (N_i, H, nu)"""
        fresh = self.population(dist.iteration) - dist.kept.shape[0]
        samples = dist.mean + dist.std * self._noise(dist, generator, fresh)
        return torch.cat([dist.kept, samples], dim=0)

    def _update(self, dist: ICEMDistribution, samples: Tensor, returns: Tensor) -> ICEMDistribution:
        order = torch.topk(returns, self.num_elites, sorted=True).indices  # (K,) best first
        elites = samples[order]  # (K, H, nu)
        elite_mean = elites.mean(dim=0)
        elite_std = elites.std(dim=0, correction=0)
        a = self.momentum
        mean = a * dist.mean + (1 - a) * elite_mean
        std = (a * dist.std + (1 - a) * elite_std).clamp_min(self.min_std)
        return ICEMDistribution(
            mean=mean, std=std, iteration=dist.iteration + 1, kept=elites[: self.num_kept]
        )
