"""The objective protocol every planner optimises, and the return helpers objectives share.

A planner sees only an `Objective`: a batch of action sequences (N, H, nu) -> their returns
(N,). An `ObjectiveFactory` makes the objective of one start state; the model objective
(`objectives/model.py`) and MuJoCo's (`objectives/mujoco.py`) are the two the package builds.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol, runtime_checkable

import torch
from torch import Tensor

Objective = Callable[[Tensor], Tensor]  # actions (N, H, nu) -> returns (N,)


@runtime_checkable
class ObjectiveFactory(Protocol):
    """(q0 (nq,), qd0 (nv,), step) -> `Objective` from that state.

    `time_indexed`: the task depends on the episode step, and the factory is called with the
    step of the first action (`step=t`). `planning_threads`: intra-op threads for the
    planner's own work while it plans on this factory (None: leave them as they are).
    `close()` releases what the factory holds (threads). A class that subclasses this
    protocol inherits the defaults (not time-indexed, None, nothing to close); a plain
    callable ``(q0, qd0) -> Objective`` is adapted by `as_objective_factory`.
    """

    time_indexed: bool = False
    planning_threads: int | None = None

    def __call__(self, q0: Tensor, qd0: Tensor, step: int = 0) -> Objective: ...

    def close(self) -> None:
        return None


class CallableFactory(ObjectiveFactory):
    """A callable that lacks some of `ObjectiveFactory`'s members, with the defaults for
    them (its own `time_indexed` and `close` where it has them)."""

    def __init__(self, make: Callable[..., Any]) -> None:
        self.make = make
        self.time_indexed = bool(getattr(make, "time_indexed", False))

    def __call__(self, q0: Tensor, qd0: Tensor, step: int = 0) -> Objective:
        return self.make(q0, qd0, step=step) if self.time_indexed else self.make(q0, qd0)

    def close(self) -> None:
        close = getattr(self.make, "close", None)
        if close is not None:
            close()


def as_objective_factory(factory: ObjectiveFactory | Callable[..., Any]) -> ObjectiveFactory:
    """`factory` itself where it has every member of `ObjectiveFactory`, else adapted
    (`CallableFactory`)."""
    return factory if isinstance(factory, ObjectiveFactory) else CallableFactory(factory)


def discounted_masked_return(rewards: Tensor, terminated: Tensor, discount: float = 1.0) -> Tensor:
    """sum_t discount^t r_t, with rewards after the first terminated step set to zero.

    The reward of the step that reaches a terminal state counts; later ones do not.
    rewards: (..., H), terminated: (..., H) bool of the reached states -> (...).
    """
    horizon = rewards.shape[-1]
    # ended_before_t: an earlier step already reached a terminal state (exclusive cumsum)
    term = terminated.to(torch.int32)
    ended_before = (torch.cumsum(term, dim=-1) - term) > 0
    rewards = torch.where(ended_before, torch.zeros_like(rewards), rewards)
    powers = discount ** torch.arange(horizon, device=rewards.device, dtype=rewards.dtype)
    return (rewards * powers).sum(dim=-1)


def risk_adjusted_return(particle_returns: Tensor, risk: float = 0.0) -> Tensor:
    """Score of each action sequence from its particles' returns: mean - risk * std.

    particle_returns: (N, P) returns of the P particles (ensemble rollouts) of each of N
    sequences -> (N,). The std is over particles with divisor P (population std), so one
    particle scores its plain return whatever `risk`. risk 0 is the plain mean over
    particles; risk > 0 prefers sequences the particles agree on (pessimism under model
    uncertainty); risk < 0 is optimistic.
    """
    if particle_returns.ndim != 2:
        raise ValueError(
            f"particle_returns must be (N, P), got shape {tuple(particle_returns.shape)}"
        )
    mean = particle_returns.mean(dim=1)  # (N,)
    if risk == 0.0 or particle_returns.shape[1] == 1:
        return mean
    return mean - risk * particle_returns.std(dim=1, correction=0)
