"""Torch forward kinematics for the rewards (batched, no simulator).

Planar chains live in the x-z plane, hang down at q = 0 and swing towards +x for positive
angles (MuJoCo hinge axes -y); joint angles are relative to the parent link.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor


def planar_chain_points(q: Tensor, link_lengths: Sequence[float]) -> Tensor:
    """Tip of every link of a planar chain hanging from the origin.

    q: (..., n) relative joint angles -> (..., n, 2) tip positions (x, z) in the world frame.
    """
    theta = torch.cumsum(q, dim=-1)  # absolute link angles from the downward vertical
    x = torch.zeros_like(q[..., 0])
    z = torch.zeros_like(q[..., 0])
    points = []
    for i, length in enumerate(link_lengths):
        x = x + length * torch.sin(theta[..., i])
        z = z - length * torch.cos(theta[..., i])
        points.append(torch.stack((x, z), dim=-1))
    return torch.stack(points, dim=-2)
