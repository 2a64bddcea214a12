"""Cart-pole swing-up (cartpole.xml): q = (cart x, pole angle), the pole hangs down at 0."""

from __future__ import annotations

import torch
from torch import Tensor

from mbrl_delan.systems.system import State
from mbrl_delan.tasks.base import Task
from mbrl_delan.tasks.common import control_factor, noisy_rest_state, velocity_factor
from mbrl_delan.tasks.pendulum import upright

# cartpole.xml
CART_MASS = 1.0  # kg
POLE_MASS = 0.1  # kg, uniform pole
POLE_LENGTH = 1.0  # m, COM at half length
CART_GEAR = 10.0  # N per unit control
CARTPOLE_DAMPING = (0.1, 0.01)  # cart N s / m, pole N m s / rad


class CartpoleSwingup(Task):
    """Swing the pole up and balance it with the cart near the origin.

    reward = upright(pole) * (1 + exp(-x^2 / (2 rail_scale^2))) / 2 * control_factor *
    velocity_factor, in [0, 1], 1 only upright at x = 0, at rest, with zero force.
    """

    def __init__(
        self,
        pole_length: float = POLE_LENGTH,
        rail_scale: float = 1.0,
        ctrl_weight: float = 0.1,
        vel_weight: float = 0.01,
        episode_len: int = 150,
        q_noise: float = 0.05,
        qd_noise: float = 0.05,
        name: str = "cartpole",
    ) -> None:
        self.name = name
        self.pole_length = float(pole_length)
        self.rail_scale = rail_scale
        self.ctrl_weight = ctrl_weight
        self.vel_weight = vel_weight
        self.episode_len = episode_len
        self.q_noise = q_noise
        self.qd_noise = qd_noise

    def tip_positions(self, q: Tensor) -> Tensor:
        """(..., 2) -> (..., 1, 2): (x, z) of the pole tip (the pivot is at the cart, z = 0)."""
        x, angle = q[..., 0], q[..., 1]
        tip = torch.stack(
            (x + self.pole_length * torch.sin(angle), -self.pole_length * torch.cos(angle)),
            dim=-1,
        )
        return tip.unsqueeze(-2)

    def reward(self, q: Tensor, qd: Tensor, action: Tensor) -> Tensor:
        """(..., 2), (..., 2), (..., 1) -> (...) in [0, 1]."""
        centered = 0.5 * (1.0 + torch.exp(-0.5 * (q[..., 0] / self.rail_scale).square()))
        shaping = control_factor(action, self.ctrl_weight) * velocity_factor(qd, self.vel_weight)
        return upright(q[..., 1]) * centered * shaping

    def initial_state(self, batch_shape: tuple[int, ...], generator: torch.Generator) -> State:
        return noisy_rest_state(2, tuple(batch_shape), generator, self.q_noise, self.qd_noise)
