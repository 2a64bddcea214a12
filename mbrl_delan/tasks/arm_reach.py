"""Reaching with a planar n-link arm (arm2 by default)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from mbrl_delan.systems.kinematics import planar_chain_points
from mbrl_delan.tasks.common import ShapedTask

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


@dataclass(kw_only=True, eq=False)
class ArmReach(ShapedTask):
    """Bring the arm's end effector to a fixed target (x, z) and hold it there.

    reward = 1 / (1 + (d / distance_scale)^2) * control_factor * velocity_factor, with d the
    tip-to-target distance: in (0, 1], exactly 1 at the target, at rest, with zero action,
    and with a gradient everywhere in the workspace.
    """

    link_lengths: Sequence[float] = ARM2_LINK_LENGTHS  # m, a tuple once built
    target: tuple[float, float] = (0.6, 0.4)  # (x, z) in m
    distance_scale: float = 0.15  # m
    ctrl_weight: float = 0.05
    episode_len: int = 80
    name: str = "arm_reach"

    def __post_init__(self) -> None:
        reach = sum(self.link_lengths)
        if (self.target[0] ** 2 + self.target[1] ** 2) ** 0.5 > reach:
            raise ValueError(f"target {self.target} is out of reach (total link length {reach})")
        self.link_lengths = tuple(float(x) for x in self.link_lengths)
        self.target = (float(self.target[0]), float(self.target[1]))

    @property
    def nq(self) -> int:
        return len(self.link_lengths)

    def markers(self) -> tuple[tuple[float, float, float], ...]:
        """The target in the world: (x, 0, z), the arm's base at the origin."""
        return ((self.target[0], 0.0, self.target[1]),)

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
        return near * self.shaping(qd, action)
