"""Reward factors and initial-state helpers shared by the tasks."""

from __future__ import annotations

import torch
from torch import Tensor

from mbrl_delan.systems.system import State


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
