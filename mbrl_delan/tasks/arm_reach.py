"""Reaching with a planar n-link arm (arm2 by default)."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from mbrl_delan.systems.kinematics import planar_chain_points
from mbrl_delan.systems.system import State
from mbrl_delan.tasks.base import Task
from mbrl_delan.tasks.common import control_factor, noisy_rest_state, velocity_factor

GRAVITY = 9.81  # m/s^2, MuJoCo's default

# arm2.xml: uniform links, COM at mid-link, inertia about the COM m l^2 / 12
ARM2_LINK_LENGTHS = (0.5, 0.5)  # m
ARM2_MASSES = (1.0, 1.0)  # kg
ARM2_GEARS = (20.0, 10.0)  # N m per unit control
ARM2_DAMPING = (0.1, 0.1)  # N m s / rad

# arm3.xml
ARM3_LINK_LENGTHS = (0.4, 0.35, 0.25)  # m
ARM3_MASSES = (1.0, 0.8, 0.5)  # kg
ARM3_GEARS = (25.0, 12.0, 4.0)  # N m per unit control
ARM3_DAMPING = (0.1, 0.1, 0.05)  # N m s / rad


class ArmReach(Task):
    """Bring the arm's end effector to a fixed target (x, z) and hold it there.

    reward = 1 / (1 + (d / distance_scale)^2) * control_factor * velocity_factor, with d the
    tip-to-target distance: in (0, 1], exactly 1 at the target, at rest, with zero action,
    and with a gradient everywhere in the workspace.
    """

    def __init__(
        self,
        link_lengths: Sequence[float] = ARM2_LINK_LENGTHS,
        target: tuple[float, float] = (0.6, 0.4),
        distance_scale: float = 0.15,
        ctrl_weight: float = 0.05,
        vel_weight: float = 0.01,
        episode_len: int = 80,
        q_noise: float = 0.05,
        qd_noise: float = 0.05,
        name: str = "arm_reach",
    ) -> None:
        reach = sum(link_lengths)
        if (target[0] ** 2 + target[1] ** 2) ** 0.5 > reach:
            raise ValueError(f"target {target} is out of reach (total link length {reach})")
        self.name = name
        self.link_lengths = tuple(float(x) for x in link_lengths)
        self.target = (float(target[0]), float(target[1]))
        self.distance_scale = distance_scale
        self.ctrl_weight = ctrl_weight
        self.vel_weight = vel_weight
        self.episode_len = episode_len
        self.q_noise = q_noise
        self.qd_noise = qd_noise

    def tip_positions(self, q: Tensor) -> Tensor:
        """(..., n) -> (..., n, 2): (x, z) of every link tip."""
        return planar_chain_points(q, self.link_lengths)

    def distance(self, q: Tensor) -> Tensor:
        """End-effector distance to the target. (..., n) -> (...)."""
        tip = self.tip_positions(q)[..., -1, :]  # (..., 2)
        dx = tip[..., 0] - self.target[0]
        dz = tip[..., 1] - self.target[1]
        return torch.sqrt(dx.square() + dz.square())

    def reward(self, q: Tensor, qd: Tensor, action: Tensor) -> Tensor:
        """(..., n), (..., n), (..., nu) -> (...) in (0, 1]."""
        tip = self.tip_positions(q)[..., -1, :]
        d2 = (tip[..., 0] - self.target[0]).square() + (tip[..., 1] - self.target[1]).square()
        near = 1.0 / (1.0 + d2 / self.distance_scale**2)
        shaping = control_factor(action, self.ctrl_weight) * velocity_factor(qd, self.vel_weight)
        return near * shaping

    def initial_state(self, batch_shape: tuple[int, ...], generator: torch.Generator) -> State:
        n = len(self.link_lengths)
        return noisy_rest_state(n, tuple(batch_shape), generator, self.q_noise, self.qd_noise)
