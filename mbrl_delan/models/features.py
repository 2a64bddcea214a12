"""Input features of q with their exact forward- and reverse-mode derivatives.

Periodic hinges map to (sin q, cos q); every other scalar coordinate is passed through.
DeLaN needs derivatives along velocities, so the map also offers a jvp (tangent along qd)
and a vjp (cotangent back to velocity space), each one cheap elementwise operation.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from mbrl_delan.systems.system import JointLayout


class QFeatures(nn.Module):
    """phi(q): (..., nq) -> (..., n_features)."""

    def __init__(self, layout: JointLayout) -> None:
        super().__init__()
        if not layout.only_scalar_joints:
            raise NotImplementedError("QFeatures supports hinge and slide joints only so far")
        nq = layout.nq
        periodic = sorted(layout.periodic_dofs)
        plain = [i for i in range(nq) if i not in set(periodic)]
        self.register_buffer("periodic", torch.tensor(periodic, dtype=torch.long), persistent=False)
        self.register_buffer("plain", torch.tensor(plain, dtype=torch.long), persistent=False)
        self.nq = nq
        self.n_features = 2 * len(periodic) + len(plain)

    def forward(self, q: Tensor) -> Tensor:
        """(..., nq) -> (..., n_features)."""
        qp = q[..., self.periodic]
        return torch.cat([torch.sin(qp), torch.cos(qp), q[..., self.plain]], dim=-1)

    def jvp(self, q: Tensor, v: Tensor) -> Tensor:
        """d phi(q) [v]: the features' rate of change along velocity v. (..., nv) -> (..., nf)."""
        qp, vp = q[..., self.periodic], v[..., self.periodic]
        return torch.cat([torch.cos(qp) * vp, -torch.sin(qp) * vp, v[..., self.plain]], dim=-1)

    def vjp(self, q: Tensor, cotangent: Tensor) -> Tensor:
        """(d phi / dq)^T cotangent: (..., nf) -> (..., nv)."""
        k = self.periodic.numel()
        qp = q[..., self.periodic]
        c_sin, c_cos, c_plain = (
            cotangent[..., :k],
            cotangent[..., k : 2 * k],
            cotangent[..., 2 * k :],
        )
        out = torch.zeros_like(q)
        out[..., self.periodic] = torch.cos(qp) * c_sin - torch.sin(qp) * c_cos
        out[..., self.plain] = c_plain
        return out
