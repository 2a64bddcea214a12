"""Pendulum swing-up (pendulum.xml)."""

from __future__ import annotations

import torch
from torch import Tensor

from mbrl_delan.systems.kinematics import planar_chain_points
from mbrl_delan.systems.system import State
from mbrl_delan.tasks.base import Task
from mbrl_delan.tasks.common import control_factor, noisy_rest_state, velocity_factor

# pendulum.xml: a bob on a massless rod
PENDULUM_LENGTH = 1.0  # m, pivot to bob (COM)
PENDULUM_MASS = 1.0  # kg
PENDULUM_INERTIA = 0.01  # kg m^2, bob about its own COM
PENDULUM_GEAR = 5.0  # N m per unit control (about 0.51 m g l: still must pump)
PENDULUM_DAMPING = 0.05  # N m s / rad


def upright(angle: Tensor) -> Tensor:
    """(1 - cos angle) / 2: 0 hanging down, 1 straight up. (...) -> (...)."""
    return 0.5 * (1.0 - torch.cos(angle))


class PendulumSwingup(Task):
    """Swing the pendulum up from hanging down and balance it.

    reward = upright(q) * control_factor(a) * velocity_factor(qd), in [0, 1], 1 only upright,
    at rest and with zero torque.
    """

    def __init__(
        self,
        length: float = PENDULUM_LENGTH,
        ctrl_weight: float = 0.1,
        vel_weight: float = 0.01,
        episode_len: int = 100,
        q_noise: float = 0.05,
        qd_noise: float = 0.05,
        name: str = "pendulum",
    ) -> None:
        self.name = name
        self.length = float(length)
        self.ctrl_weight = ctrl_weight
        self.vel_weight = vel_weight
        self.episode_len = episode_len
        self.q_noise = q_noise
        self.qd_noise = qd_noise

    def tip_positions(self, q: Tensor) -> Tensor:
        """(..., 1) -> (..., 1, 2): (x, z) of the bob."""
        return planar_chain_points(q, (self.length,))

    def reward(self, q: Tensor, qd: Tensor, action: Tensor) -> Tensor:
        """(..., 1), (..., 1), (..., 1) -> (...) in [0, 1]."""
        up = upright(q[..., 0])
        return up * control_factor(action, self.ctrl_weight) * velocity_factor(qd, self.vel_weight)

    def initial_state(self, batch_shape: tuple[int, ...], generator: torch.Generator) -> State:
        return noisy_rest_state(1, tuple(batch_shape), generator, self.q_noise, self.qd_noise)
