"""Cart-pole swing-up (cartpole.xml): q = (cart x, pole angle), the pole hangs down at 0."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from mbrl_delan.tasks.common import ShapedTask
from mbrl_delan.tasks.pendulum import upright

# cartpole.xml
CART_MASS = 1.0  # kg
POLE_MASS = 0.1  # kg, uniform pole
POLE_LENGTH = 1.0  # m, COM at half length
CART_GEAR = 10.0  # N per unit control
CARTPOLE_DAMPING = (0.1, 0.01)  # cart N s / m, pole N m s / rad


@dataclass(kw_only=True, eq=False)
class CartpoleSwingup(ShapedTask):
    """Swing the pole up and balance it with the cart near the origin.

    reward = upright(pole) * (1 + exp(-x^2 / (2 rail_scale^2))) / 2 * control_factor *
    velocity_factor, in [0, 1], 1 only upright at x = 0, at rest, with zero force.
    """

    pole_length: float = POLE_LENGTH  # m
    rail_scale: float = 1.0  # m, width of the centring factor
    episode_len: int = 150
    name: str = "cartpole"
    nq = 2

    def __post_init__(self) -> None:
        self.pole_length = float(self.pole_length)

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
        return upright(q[..., 1]) * centered * self.shaping(qd, action)
