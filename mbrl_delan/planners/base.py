"""Batched functional sampling planners: the contract and the shared machinery.

A planner sees only an objective, a callable mapping a batch of action sequences to their
returns, `(N, H, nu) -> (N,)`, and improves a sampling distribution over a few iterations.
Subclasses implement `_initial_distribution`, `_sample` and `_update`, and may override
`_noise` (iCEM: colored noise), `_warm_distribution` (state carried from the previous call,
passed to `plan` as keyword arguments: iCEM's kept elites) and `_result` (extra result
fields), all without touching the loop in `plan`.
"""

from __future__ import annotations

import abc
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, fields, replace
from typing import Any, ClassVar, Protocol

import torch
from omegaconf import MISSING, DictConfig
from torch import Tensor

from mbrl_delan.objectives.base import Objective
from mbrl_delan.planners.spline import INTERPOLATIONS, KnotSpline
from mbrl_delan.registry import register_planner
from mbrl_delan.rules import rule
from mbrl_delan.systems.system import System

SHIFT_FILLS = ("repeat", "zero")


@dataclass
class SamplingSettings:
    """What every sampling planner takes beside its horizon and action bounds, each typed,
    ranged and defaulted here once: the planner's constructor takes them (a settings object
    and/or keyword changes) and the planner groups' schemas (`PlannerConfig`'s kin) extend
    them.

    num_samples: sequences N evaluated per iteration. iterations: refinement iterations per
    `plan` call. knots: the planner searches K knots (K, nu) of a spline over the horizon
    instead of every step's action (`KnotSpline`; the objective still gets (N, H, nu)); None:
    every step is a knot. interpolation: how the actions between knots follow from them
    (`INTERPOLATIONS`). shift_fill: how `shift` fills the freed last step: "repeat" the last
    action or "zero" (zero clamped into the bounds).
    """

    num_samples: int = rule(256, low=1)
    iterations: int = rule(4, low=1)
    knots: int | None = rule(None, low=1)
    interpolation: str = rule("linear", choices=INTERPOLATIONS)
    shift_fill: str = rule("repeat", choices=SHIFT_FILLS)


@dataclass
class PlanResult:
    """What one call of `plan` found."""

    mean: Tensor  # (H, nu) final mean of the sampling distribution, within bounds
    std: Tensor  # (H, nu) final spread of the sampling distribution
    best_actions: Tensor  # (H, nu) the best sequence sampled in any iteration
    best_return: Tensor  # () its return
    iteration_best: Tensor  # (iterations,) best sampled return per iteration

    @property
    def first_action(self) -> Tensor:
        """The action to execute now: the first step of the mean. (nu,)"""
        return self.mean[0]


@dataclass
class SamplingDistribution:
    """State of the sampling distribution between iterations."""

    mean: Tensor  # (K, nu) knots (K = H without a spline)
    std: Tensor  # (K, nu)


@dataclass
class PlanTrace:
    """What the iterations of one `plan` call have seen so far."""

    best_actions: Tensor  # (H, nu) best sequence sampled so far (the start mean before any)
    best_return: Tensor | None = None  # () its return; None before the first iteration
    iteration_best: list[Tensor] = field(default_factory=list)  # () per iteration
    population: list[int] = field(default_factory=list)  # objective batch size per iteration

    def record(self, samples: Tensor, returns: Tensor) -> None:
        """Add one iteration's samples (N, H, nu) and cleaned returns (N,), without a host sync."""
        idx = torch.argmax(returns)
        it_best = returns[idx]
        if self.best_return is None:
            self.best_actions, self.best_return = samples[idx], it_best
        else:
            better = it_best > self.best_return
            self.best_actions = torch.where(better, samples[idx], self.best_actions)
            self.best_return = torch.where(better, it_best, self.best_return)
        self.iteration_best.append(it_best)
        self.population.append(samples.shape[0])


def as_bound(value: Tensor | Sequence[float] | float, name: str) -> Tensor:
    """A 1-D float64 CPU tensor from an action bound given as a tensor, list or scalar."""
    bound = torch.as_tensor(value, dtype=torch.float64).detach().cpu().reshape(-1)
    if bound.numel() == 0:
        raise ValueError(f"{name} must have at least one element, got {value!r}")
    if torch.isnan(bound).any():
        raise ValueError(f"{name} must not contain NaN, got {bound.tolist()}")
    return bound


def require(condition: bool, message: str) -> None:
    """Raise ValueError(message) when a constructor argument is invalid."""
    if not condition:
        raise ValueError(message)


def clean_returns(returns: Tensor, num_samples: int) -> Tensor:
    """Check the objective's output and map NaN to -inf and +inf to the largest float. (N,)"""
    if returns.shape != (num_samples,):
        raise ValueError(
            f"objective must return shape ({num_samples},), got {tuple(returns.shape)}"
        )
    if not returns.is_floating_point():
        returns = returns.double()
    big = torch.finfo(returns.dtype).max
    return torch.nan_to_num(returns, nan=-math.inf, posinf=big, neginf=-math.inf)


class Planner(Protocol):
    """What `PlannerPolicy` runs: a planner over plans (H, nu), warm-started by shifting
    (its methods' names, `mbrl_delan.registry.PLANNER_METHODS`, are checked when a planner
    is registered with its class and when one is built).

    `plan(problem, init, generator, **warm)` returns a result whose `mean` (H, nu) is the plan
    to execute and whose `best_return` is logged. `problem` is what the policy's factory made
    for the current state: an objective over (N, H, nu) for the sampling planners
    (`SamplingPlanner`), a start state for iLQR (`ILQRPlanner`)."""

    horizon: int

    def initial_mean(self, device: torch.device | str | None = None) -> Tensor: ...

    def shift(self, mean: Tensor, steps: int) -> Tensor: ...

    def carry(self, result: Any) -> dict[str, Tensor]: ...

    def warm_start(self, carried: dict[str, Tensor], steps: int) -> dict[str, Any]: ...

    def plan(
        self, problem: Any, init_mean: Tensor, generator: torch.Generator, **warm: Any
    ) -> Any: ...


class SamplingPlanner(abc.ABC):
    """Shared loop, bounds, validation and warm-start shifting of the sampling planners.

    Args:
        horizon: planning horizon H in control steps (>= 1).
        action_low: lower bound of each action dimension, shape (nu,); may be -inf.
            Every sampled sequence is clamped into the bounds.
        action_high: upper bound of each action dimension, shape (nu,); may be inf.
        settings: the planner's `Settings` (None: their defaults).
        dtype: floating dtype of the plans `initial_mean` makes.
        **changes: settings changed from `settings` by name (``num_samples=64``).

    A subclass names its settings class (`Settings`), the field that holds the first
    iteration's standard deviation (`STD_FIELD`: a scalar or (nu,); None: a quarter of the
    action range where it is finite and 1 elsewhere) and checks and takes its own fields in
    `_take`.
    """

    Settings: ClassVar[type[SamplingSettings]] = SamplingSettings
    STD_FIELD: ClassVar[str] = "init_std"

    def __init__(
        self,
        horizon: int,
        action_low: Tensor | Sequence[float] | float,
        action_high: Tensor | Sequence[float] | float,
        settings: SamplingSettings | None = None,
        dtype: torch.dtype = torch.float32,
        **changes: Any,
    ) -> None:
        if settings is not None and not isinstance(settings, self.Settings):
            raise TypeError(
                f"{type(self).__name__}: settings must be a {self.Settings.__name__}, got "
                f"{settings!r}; give single settings by name (num_samples=...)"
            )
        settings = replace(settings or self.Settings(), **changes)
        self.settings = settings
        require(horizon >= 1, f"horizon must be >= 1, got {horizon}")
        require(settings.num_samples >= 1, f"num_samples must be >= 1, got {settings.num_samples}")
        require(settings.iterations >= 1, f"iterations must be >= 1, got {settings.iterations}")
        require(
            settings.shift_fill in SHIFT_FILLS,
            f"shift_fill must be one of {SHIFT_FILLS}, got {settings.shift_fill!r}",
        )
        require(dtype.is_floating_point, f"dtype must be a floating dtype, got {dtype}")
        low, high = as_bound(action_low, "action_low"), as_bound(action_high, "action_high")
        require(
            low.shape == high.shape,
            f"action_low and action_high differ in shape: "
            f"{tuple(low.shape)} vs {tuple(high.shape)}",
        )
        require(
            bool((low <= high).all()),
            f"action_low must be <= action_high, got {low.tolist()} > {high.tolist()}",
        )
        self.horizon = horizon
        self.num_samples = settings.num_samples
        self.iterations = settings.iterations
        self.shift_fill = settings.shift_fill
        self.dtype = dtype
        self.action_low = low  # (nu,) float64 CPU
        self.action_high = high  # (nu,)
        self.init_std = self._make_init_std(getattr(settings, self.STD_FIELD, None))  # (nu,)
        self.spline = KnotSpline(horizon, settings.knots, settings.interpolation)
        self._bounds_cache: dict[tuple[torch.device, torch.dtype], tuple[Tensor, Tensor]] = {}
        self._take(settings)

    def _take(self, settings: Any) -> None:  # noqa: B027 (optional: a subclass may add none)
        """Check and keep the subclass's own settings (the base has none)."""

    @property
    def action_dim(self) -> int:
        return self.action_low.numel()

    def _make_init_std(self, init_std: float | Sequence[float] | None) -> Tensor:
        if init_std is None:
            width = self.action_high - self.action_low
            return torch.where(torch.isfinite(width) & (width > 0), width / 4, 1.0)
        std = torch.as_tensor(init_std, dtype=torch.float64).reshape(-1).expand(self.action_dim)
        require(
            bool((std > 0).all()) and bool(torch.isfinite(std).all()),
            f"init_std must be finite and > 0, got {init_std!r}",
        )
        return std.clone()

    # ------------------------------------------------------------------ helpers
    def bounds(self, like: Tensor) -> tuple[Tensor, Tensor]:
        """Action bounds on `like`'s device and dtype (cached). -> ((nu,), (nu,))"""
        key = (like.device, like.dtype)
        if key not in self._bounds_cache:
            with torch.inference_mode(False):  # normal tensors, usable in and out of it
                self._bounds_cache[key] = (
                    self.action_low.to(like.device, like.dtype),
                    self.action_high.to(like.device, like.dtype),
                )
        return self._bounds_cache[key]

    def clamp(self, actions: Tensor) -> Tensor:
        """Clamp actions (..., nu) into the bounds."""
        low, high = self.bounds(actions)
        return torch.clamp(actions, low, high)

    def initial_mean(
        self, device: torch.device | str | None = None, dtype: torch.dtype | None = None
    ) -> Tensor:
        """The cold-start plan: zero actions clamped into the bounds. (H, nu)"""
        zeros = torch.zeros(self.horizon, self.action_dim, device=device, dtype=dtype or self.dtype)
        return self.clamp(zeros)

    def shift(self, mean: Tensor, steps: int = 1) -> Tensor:
        """Warm start: drop the first `steps` actions and fill the end per `shift_fill`.

        mean: (H, nu) -> (H, nu).
        """
        require(steps >= 0, f"steps must be >= 0, got {steps}")
        self._check_mean(mean)
        if steps == 0:
            return mean.clone()
        kept = mean[min(steps, self.horizon) :]
        n_fill = self.horizon - kept.shape[0]
        if self.shift_fill == "repeat":
            fill = mean[-1:].expand(n_fill, -1)
        else:
            fill = self.clamp(
                torch.zeros(n_fill, self.action_dim, device=mean.device, dtype=mean.dtype)
            )
        return torch.cat([kept, fill], dim=0)

    def carry(self, result: PlanResult) -> dict[str, Tensor]:
        """What a receding-horizon caller keeps from a plan for the next one (beyond the mean)."""
        return {}

    def warm_start(self, carried: dict[str, Tensor], steps: int) -> dict[str, Tensor]:
        """Extra `plan` arguments from what was carried, `steps` control steps later."""
        return {}

    def _check_mean(self, mean: Tensor) -> None:
        expected = (self.horizon, self.action_dim)
        if tuple(mean.shape) != expected:
            raise ValueError(f"plan mean must have shape {expected}, got {tuple(mean.shape)}")
        if not mean.is_floating_point():
            raise ValueError(f"plan mean must be floating point, got {mean.dtype}")

    # ------------------------------------------------------------------ the loop
    def plan(
        self,
        objective: Objective,
        init_mean: Tensor | None = None,
        generator: torch.Generator | None = None,
        **warm: Tensor | None,
    ) -> PlanResult:
        """Optimise the action sequence for `objective`.

        Args:
            objective: actions (N, H, nu) -> returns (N,); higher is better. NaN counts as
                -inf.
            init_mean: (H, nu) warm start; its device and dtype are the planner's for this
                call. None: `initial_mean` on the generator's device.
            generator: source of all randomness (on the planning device).
            **warm: planner-specific warm-start state (what `warm_start` returns), handed to
                `_warm_distribution`; the base planners take none.
        """
        with torch.inference_mode():
            if init_mean is None:
                device = generator.device if generator is not None else None
                init_mean = self.initial_mean(device=device)
            self._check_mean(init_mean)
            knots = self.spline.knots_of(self.clamp(init_mean))  # (K, nu)
            dist = self._initial_distribution(knots)
            dist = self._warm_distribution(dist, **warm)
            trace = PlanTrace(best_actions=self._actions(dist.mean))
            for _ in range(self.iterations):
                samples = self.clamp(self._sample(dist, generator))  # (N_i, K, nu)
                actions = self._actions(samples)  # (N_i, H, nu)
                returns = clean_returns(objective(actions), samples.shape[0])  # (N_i,)
                dist = self._update(dist, samples, returns)
                trace.record(actions, returns)
            return self._result(dist, trace)

    def _actions(self, knots: Tensor) -> Tensor:
        """Every step's actions of knots (..., K, nu), within the bounds. (..., H, nu)"""
        if self.spline.identity:
            return knots  # clamped already
        return self.clamp(self.spline.actions(knots))

    def _warm_distribution(self, dist: SamplingDistribution) -> SamplingDistribution:
        """The first iteration's distribution given the warm-start state of `plan(**warm)`.

        Subclasses that carry state between calls (iCEM's kept elites) take it as keyword
        arguments here; the base takes none, so an unknown keyword is a TypeError.
        """
        return dist

    def _result(self, dist: SamplingDistribution, trace: PlanTrace) -> PlanResult:
        """What `plan` returns from the final distribution and the iterations' trace."""
        return PlanResult(
            mean=self._actions(self.clamp(dist.mean)),
            std=self.spline.actions(dist.std),
            best_actions=trace.best_actions,
            best_return=trace.best_return,
            iteration_best=torch.stack(trace.iteration_best),
        )

    def _noise(
        self, dist: SamplingDistribution, generator: torch.Generator | None, num: int
    ) -> Tensor:
        """White Gaussian noise (num, K, nu) on the distribution's device. iCEM overrides."""
        return torch.randn(
            (num, *dist.mean.shape),
            generator=generator,
            device=dist.mean.device,
            dtype=dist.mean.dtype,
        )

    def _sample(self, dist: SamplingDistribution, generator: torch.Generator | None) -> Tensor:
        """Draw N knot sequences (N, K, nu) around the distribution; the loop clamps them."""
        return dist.mean + dist.std * self._noise(dist, generator, self.num_samples)

    @abc.abstractmethod
    def _initial_distribution(self, mean: Tensor) -> SamplingDistribution:
        """Sampling distribution of the first iteration around the knots `mean` (K, nu)."""

    @abc.abstractmethod
    def _update(
        self, dist: SamplingDistribution, samples: Tensor, returns: Tensor
    ) -> SamplingDistribution:
        """New distribution from knot samples (N, K, nu) and their cleaned returns (N,)."""


@dataclass
class PlannerConfig(SamplingSettings):
    """What every planner group has (the receding-horizon policy and the objective read it):
    the sampling settings and the loop's; each planner's group schema extends it with its
    own settings first (``class MPPIConfig(MPPISettings, PlannerConfig)``), so that their
    defaults stand. A user's planner schema extends it too.

    horizon: control steps planned. replan_every: control steps between plans. discount:
    the objective's per-step discount in (0, 1]. risk: ensembles score mean - risk * std of
    their particles' returns."""

    name: str = MISSING
    horizon: int = rule(low=1)
    replan_every: int = rule(1, low=1)
    discount: float = rule(1.0, low=0, above=True, high=1)
    risk: float = rule(0.0)


PlannerBuilder = Callable[[DictConfig, System, torch.dtype], Planner]


def sampling_builder(planner: type[SamplingPlanner]) -> PlannerBuilder:
    """The builder of a `SamplingPlanner` subclass (the package's and a user's): its
    `Settings` read from the planner group (typed by a schema that extends them)."""

    def build(cfg: DictConfig, system: System, dtype: torch.dtype) -> SamplingPlanner:
        settings = planner.Settings(**{f.name: cfg[f.name] for f in fields(planner.Settings)})
        return planner(cfg.horizon, system.ctrl_low, system.ctrl_high, settings, dtype)

    build.planner = planner  # type: ignore[attr-defined]  # checked when registered
    return build


def register_sampling_planner(name: str, schema: type[PlannerConfig]) -> Callable[[type], type]:
    """Class decorator: register a `SamplingPlanner` subclass as planner `name`, its group
    typed by `schema`, built by `sampling_builder` (checked as a user's planner is)."""

    def add(planner: type[SamplingPlanner]) -> type[SamplingPlanner]:
        register_planner(name, schema)(sampling_builder(planner))
        return planner

    return add
