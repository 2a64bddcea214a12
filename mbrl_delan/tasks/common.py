"""Reward factors and initial-state helpers shared by the tasks."""

from __future__ import annotations

import abc
from dataclasses import dataclass

import torch
from torch import Tensor

from mbrl_delan.systems.system import State
from mbrl_delan.tasks.base import Task


class PlacedConstants:
    """A task's constant tensors, copied once to each (device, dtype) a call meets: floating
    ones take that dtype, integer ones (indices) keep theirs.

    Rewards computed on a GPU then read device copies instead of copying from the host at
    every call (such copies wait for the device, and a CUDA graph cannot capture them).
    """

    def __init__(self, **values: Tensor) -> None:
        self.values = values
        self._placed: dict[tuple[torch.device, torch.dtype], dict[str, Tensor]] = {}

    def on(self, like: Tensor) -> dict[str, Tensor]:
        """The constants on `like`'s device, in its dtype."""
        key = (like.device, like.dtype)
        if key not in self._placed:
            self._placed[key] = {
                name: v.to(like) if v.is_floating_point() else v.to(like.device)
                for name, v in self.values.items()
            }
        return self._placed[key]


def control_factor(action: Tensor, weight: float) -> Tensor:
    """exp(-weight * mean(action^2)) in (0, 1], 1 at zero action. (..., nu) -> (...)."""
    return torch.exp(-weight * action.square().mean(dim=-1))


def velocity_factor(qd: Tensor, weight: float) -> Tensor:
    """exp(-weight * mean(qd^2)) in (0, 1], 1 at rest. (..., nv) -> (...)."""
    return torch.exp(-weight * qd.square().mean(dim=-1))


def noisy_rest_state(
    nq: int,
    batch_shape: tuple[int, ...],
    generator: torch.Generator,
    q_noise: float,
    qd_noise: float,
) -> State:
    """q = 0 (hanging down, at rest) plus Gaussian noise, float64 on the generator's device."""
    shape = (*batch_shape, nq)
    kwargs = {"generator": generator, "dtype": torch.float64, "device": generator.device}
    q = q_noise * torch.randn(shape, **kwargs)
    qd = qd_noise * torch.randn(shape, **kwargs)
    return State(q=q, qd=qd)


@dataclass(kw_only=True, eq=False)
class ShapedTask(Task):
    """A task whose reward is a goal term times `shaping`, started near rest at q = 0.

    Subclasses declare their own fields and defaults (a dataclass each, keyword-only
    arguments) and the number of coordinates `nq`.
    """

    ctrl_weight: float = 0.1  # of control_factor
    vel_weight: float = 0.01  # of velocity_factor
    episode_len: int = 100  # control steps per episode
    q_noise: float = 0.05  # std of the start's q about 0 (rad or m)
    qd_noise: float = 0.05  # std of the start's qd about 0

    @property
    @abc.abstractmethod
    def nq(self) -> int:
        """Number of position coordinates of the system."""

    def shaping(self, qd: Tensor, action: Tensor) -> Tensor:
        """control_factor(action) * velocity_factor(qd). (..., nv), (..., nu) -> (...)."""
        return control_factor(action, self.ctrl_weight) * velocity_factor(qd, self.vel_weight)

    def initial_state(self, batch_shape: tuple[int, ...], generator: torch.Generator) -> State:
        return noisy_rest_state(self.nq, tuple(batch_shape), generator, self.q_noise, self.qd_noise)
