"""Acrobot swing-up (acrobot.xml): two links, only the elbow actuated."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from mbrl_delan.systems.kinematics import planar_chain_points
from mbrl_delan.systems.system import State
from mbrl_delan.tasks.base import Task
from mbrl_delan.tasks.common import control_factor, noisy_rest_state, velocity_factor

# acrobot.xml: uniform links, COM at mid-link
ACROBOT_LINK_LENGTHS = (1.0, 1.0)  # m
ACROBOT_MASSES = (1.0, 1.0)  # kg
ACROBOT_GEAR = 5.0  # N m per unit control, elbow only
ACROBOT_DAMPING = (0.05, 0.05)  # N m s / rad


class AcrobotSwingup(Task):
    """Swing both links up (the tip as high as it goes) and hold them there.

    reward = h_elbow * h_tip * control_factor * velocity_factor, with h = (z + L) / (2 L) the
    height of the elbow (L = l1) and of the tip (L = l1 + l2) mapped to [0, 1]. The product
    is in [0, 1], 1 only straight up, at rest, with zero torque; unlike the tip height alone
    it gives nothing for folding the lower link up while the upper one hangs (a local optimum
    that traps sampling planners).
    """

    def __init__(
        self,
        link_lengths: Sequence[float] = ACROBOT_LINK_LENGTHS,
        ctrl_weight: float = 0.1,
        vel_weight: float = 0.005,
        episode_len: int = 200,
        q_noise: float = 0.05,
        qd_noise: float = 0.05,
        name: str = "acrobot",
    ) -> None:
        self.name = name
        self.link_lengths = tuple(float(x) for x in link_lengths)
        self.ctrl_weight = ctrl_weight
        self.vel_weight = vel_weight
        self.episode_len = episode_len
        self.q_noise = q_noise
        self.qd_noise = qd_noise

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
        shaping = control_factor(action, self.ctrl_weight) * velocity_factor(qd, self.vel_weight)
        return self.heights(q).prod(dim=-1) * shaping

    def initial_state(self, batch_shape: tuple[int, ...], generator: torch.Generator) -> State:
        return noisy_rest_state(2, tuple(batch_shape), generator, self.q_noise, self.qd_noise)
