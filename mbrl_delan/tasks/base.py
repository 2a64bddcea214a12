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
    """

    name: str
    episode_len: int  # control steps per episode (then truncated)

    @abc.abstractmethod
    def reward(self, q: Tensor, qd: Tensor, action: Tensor) -> Tensor:
        """(..., nq), (..., nv), (..., nu) -> (...)."""

    def terminated(self, q: Tensor, qd: Tensor) -> Tensor:
        """(..., nq), (..., nv) -> (...) bool. Default: never terminates."""
        return torch.zeros(q.shape[:-1], dtype=torch.bool, device=q.device)

    @abc.abstractmethod
    def initial_state(self, batch_shape: tuple[int, ...], generator: torch.Generator) -> State:
        """Initial states, float64 on the generator's device: State((*B, nq), (*B, nv))."""
