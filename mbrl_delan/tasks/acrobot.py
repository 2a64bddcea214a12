"""Acrobot swing-up (acrobot.xml): two links, only the elbow actuated."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from mbrl_delan.systems.kinematics import planar_chain_points
from mbrl_delan.tasks.common import ShapedTask

# acrobot.xml: uniform links, COM at mid-link
ACROBOT_LINK_LENGTHS = (1.0, 1.0)  # m
ACROBOT_MASSES = (1.0, 1.0)  # kg
ACROBOT_GEAR = 5.0  # N m per unit control, elbow only
ACROBOT_DAMPING = (0.05, 0.05)  # N m s / rad


@dataclass(kw_only=True, eq=False)
class AcrobotSwingup(ShapedTask):
    """Swing both links up (the tip as high as it goes) and hold them there.

    reward = h_elbow * h_tip * control_factor * velocity_factor, with h = (z + L) / (2 L) the
    height of the elbow (L = l1) and of the tip (L = l1 + l2) mapped to [0, 1]. The product
    is in [0, 1], 1 only straight up, at rest, with zero torque; unlike the tip height alone
    it gives nothing for folding the lower link up while the upper one hangs (a local optimum
    that traps sampling planners).
    """

    link_lengths: Sequence[float] = ACROBOT_LINK_LENGTHS  # m, a tuple once built
    vel_weight: float = 0.005
    episode_len: int = 200
    name: str = "acrobot"

    def __post_init__(self) -> None:
        self.link_lengths = tuple(float(x) for x in self.link_lengths)

    @property
    def nq(self) -> int:
        return len(self.link_lengths)

    def tip_positions(self, q: Tensor) -> Tensor:
        """(..., 2) -> (..., 2, 2): (x, z) of the elbow and of the tip."""
        return planar_chain_points(q, self.link_lengths)

    def heights(self, q: Tensor) -> Tensor:
        """Elbow and tip heights, each mapped to [0, 1]. (..., 2) -> (..., 2)."""
        l1, l2 = self.link_lengths
        z = self.tip_positions(q)[..., 1]  # (..., 2)
        elbow = 0.5 * (1.0 + z[..., 0] / l1)
        tip = 0.5 * (1.0 + z[..., 1] / (l1 + l2))
        return torch.stack((elbow, tip), dim=-1)

    def reward(self, q: Tensor, qd: Tensor, action: Tensor) -> Tensor:
        """(..., 2), (..., 2), (..., 1) -> (...) in [0, 1]."""
        return self.heights(q).prod(dim=-1) * self.shaping(qd, action)
