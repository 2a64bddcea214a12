"""The task contract: reward, termination and initial states as pure torch functions."""

from __future__ import annotations

import abc

import torch
from torch import Tensor

from mbrl_delan.systems.system import State


class Task(abc.ABC):
    """A task on a system. Every method is batched over any leading dims and calls no simulator.

    The reward of a transition is scored on the state it reaches and the action taken:
    r_t = reward(q_{t+1}, qd_{t+1}, a_t).

    A time-indexed task (`time_indexed = True`, e.g. following a reference motion) also
    depends on the episode step t of the action: r_t = reward_at(q_{t+1}, qd_{t+1}, a_t, t)
    and termination terminated_at(q_{t+1}, qd_{t+1}, t). Every caller (the real env, the
    oracle, the model objective) calls `reward_at` / `terminated_at`; for a task that does not
    depend on time they are `reward` / `terminated`.
    """

    name: str
    episode_len: int  # control steps per episode (then truncated)
    time_indexed: bool = False

    @abc.abstractmethod
    def reward(self, q: Tensor, qd: Tensor, action: Tensor) -> Tensor:
        """(..., nq), (..., nv), (..., nu) -> (...)."""

    def terminated(self, q: Tensor, qd: Tensor) -> Tensor:
        """(..., nq), (..., nv) -> (...) bool. Default: never terminates."""
        return torch.zeros(q.shape[:-1], dtype=torch.bool, device=q.device)

    def reward_at(self, q: Tensor, qd: Tensor, action: Tensor, step: Tensor) -> Tensor:
        """Reward of the action taken at episode step `step` (int64, broadcastable to (...)).

        (..., nq), (..., nv), (..., nu), step -> (...). Default: `reward`, time ignored.
        """
        return self.reward(q, qd, action)

    def terminated_at(self, q: Tensor, qd: Tensor, step: Tensor) -> Tensor:
        """Termination of the state reached by the action of step `step`. Default: `terminated`."""
        return self.terminated(q, qd)

    def markers(self) -> tuple[tuple[float, float, float], ...]:
        """World points (x, y, z) the task aims at, drawn in videos (a reach target). Default:
        none."""
        return ()

    @abc.abstractmethod
    def initial_state(self, batch_shape: tuple[int, ...], generator: torch.Generator) -> State:
        """Initial states, float64 on the generator's device: State((*B, nq), (*B, nv))."""
