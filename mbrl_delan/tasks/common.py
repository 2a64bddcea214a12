"""Reward factors and initial-state helpers shared by the tasks."""

from __future__ import annotations

import torch
from torch import Tensor

from mbrl_delan.systems.system import State


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
