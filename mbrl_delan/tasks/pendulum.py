"""Pendulum swing-up (pendulum.xml)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from mbrl_delan.systems.kinematics import planar_chain_points
from mbrl_delan.tasks.common import ShapedTask

# pendulum.xml: a bob on a massless rod
PENDULUM_LENGTH = 1.0  # m, pivot to bob (COM)
PENDULUM_MASS = 1.0  # kg
PENDULUM_INERTIA = 0.01  # kg m^2, bob about its own COM
PENDULUM_GEAR = 5.0  # N m per unit control (about 0.51 m g l: still must pump)
PENDULUM_DAMPING = 0.05  # N m s / rad


def upright(angle: Tensor) -> Tensor:
    """(1 - cos angle) / 2: 0 hanging down, 1 straight up. (...) -> (...)."""
    return 0.5 * (1.0 - torch.cos(angle))


@dataclass(kw_only=True, eq=False)
class PendulumSwingup(ShapedTask):
    """Swing the pendulum up from hanging down and balance it.

    reward = upright(q) * control_factor(a) * velocity_factor(qd), in [0, 1], 1 only upright,
    at rest and with zero torque.
    """

    length: float = PENDULUM_LENGTH  # m, pivot to bob
    name: str = "pendulum"
    nq = 1

    def __post_init__(self) -> None:
        self.length = float(self.length)

    def tip_positions(self, q: Tensor) -> Tensor:
        """(..., 1) -> (..., 1, 2): (x, z) of the bob."""
        return planar_chain_points(q, (self.length,))

    def reward(self, q: Tensor, qd: Tensor, action: Tensor) -> Tensor:
        """(..., 1), (..., 1), (..., 1) -> (...) in [0, 1]."""
        return upright(q[..., 0]) * self.shaping(qd, action)
