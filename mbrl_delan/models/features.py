"""Input features of q with their exact forward- and reverse-mode derivatives in velocity space.

Per joint (MuJoCo layout):
- unlimited hinge: (sin q, cos q);
- limited hinge, slide: q itself;
- ball: the 9 entries of its rotation matrix R (smooth, and blind to the quaternion's sign);
- free: the root height z and R; the x/y position is left out (the physics does not depend
  on it), unless `translation_invariant=False`.

DeLaN differentiates the features along a generalized velocity. Angular velocities of ball
and free joints are body-frame (quasi-velocities), so the derivative of R along omega is
R [omega]x, the derivative of q (+) eps v at eps = 0 (`integrate_pos`). `jvp` carries a
velocity to the features' rate of change; `vjp` brings a cotangent on the features back to
velocity space. Both are a few elementwise operations.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from mbrl_delan.systems.system import BALL, FREE, HINGE, JointLayout


def rotation_matrix(quat: Tensor) -> Tensor:
    """Unit-normalised quaternion (..., 4) as (w, x, y, z) -> rotation matrix (..., 3, 3)."""
    w, x, y, z = (quat / quat.norm(dim=-1, keepdim=True)).unbind(-1)
    rows = (
        (1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)),
        (2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)),
        (2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)),
    )
    return torch.stack([torch.stack(r, dim=-1) for r in rows], dim=-2)


def skew(v: Tensor) -> Tensor:
    """(..., 3) -> (..., 3, 3) with skew(v) u = v x u."""
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    rows = ((o, -z, y), (z, o, -x), (-y, x, o))
    return torch.stack([torch.stack(r, dim=-1) for r in rows], dim=-2)


def unskew_of_rt(R: Tensor, G: Tensor) -> Tensor:
    """The omega-cotangent of a cotangent G on R, for dR = R [omega]x. (..., 3, 3) -> (..., 3)."""
    A = R.transpose(-1, -2) @ G
    return torch.stack(
        (A[..., 2, 1] - A[..., 1, 2], A[..., 0, 2] - A[..., 2, 0], A[..., 1, 0] - A[..., 0, 1]),
        dim=-1,
    )


class QFeatures(nn.Module):
    """phi(q): (..., nq) -> (..., n_features), with jvp/vjp in velocity space (nv)."""

    def __init__(self, layout: JointLayout, translation_invariant: bool = True) -> None:
        super().__init__()
        periodic, plain_q, plain_v, rotations, positions = [], [], [], [], []
        for jtype, qa, va, limited in zip(
            layout.types, layout.qpos_adr, layout.dof_adr, layout.limited, strict=True
        ):
            if jtype == HINGE and not limited:
                periodic.append((qa, va))
            elif jtype == FREE:
                coords = (2,) if translation_invariant else (0, 1, 2)
                positions += [(qa + k, va + k) for k in coords]
                rotations.append((qa + 3, va + 3))
            elif jtype == BALL:
                rotations.append((qa, va))
            else:  # slide, limited hinge
                plain_q.append(qa)
                plain_v.append(va)
        plain_q += [p[0] for p in positions]
        plain_v += [p[1] for p in positions]
        self._index("periodic_q", [p[0] for p in periodic])
        self._index("periodic_v", [p[1] for p in periodic])
        self._index("plain_q", plain_q)
        self._index("plain_v", plain_v)
        self._index("rot_q", [[r[0] + k for k in range(4)] for r in rotations], (0, 4))
        self._index("rot_v", [[r[1] + k for k in range(3)] for r in rotations], (0, 3))
        self.n_periodic, self.n_plain, self.n_rot = len(periodic), len(plain_q), len(rotations)
        self.nq, self.nv = layout.nq, layout.nv
        self.n_features = 2 * self.n_periodic + self.n_plain + 9 * self.n_rot

    def _index(self, name: str, values: list, empty_shape: tuple[int, ...] = (0,)) -> None:
        t = torch.tensor(values, dtype=torch.long) if values else torch.zeros(empty_shape).long()
        self.register_buffer(name, t, persistent=False)

    def _rotations(self, q: Tensor) -> Tensor:
        """(..., nq) -> (..., K, 3, 3)."""
        return rotation_matrix(q[..., self.rot_q])

    def forward(self, q: Tensor) -> Tensor:
        """(..., nq) -> (..., n_features)."""
        qp = q[..., self.periodic_q]
        parts = [torch.sin(qp), torch.cos(qp), q[..., self.plain_q]]
        if self.n_rot:
            parts.append(self._rotations(q).flatten(-3))
        return torch.cat(parts, dim=-1)

    def jvp(self, q: Tensor, v: Tensor) -> Tensor:
        """d phi(q (+) eps v) / d eps at 0: (..., nq), (..., nv) -> (..., n_features)."""
        qp, vp = q[..., self.periodic_q], v[..., self.periodic_v]
        parts = [torch.cos(qp) * vp, -torch.sin(qp) * vp, v[..., self.plain_v]]
        if self.n_rot:
            R = self._rotations(q)
            parts.append((R @ skew(v[..., self.rot_v])).flatten(-3))
        return torch.cat(parts, dim=-1)

    def vjp(self, q: Tensor, cotangent: Tensor) -> Tensor:
        """Cotangent on the features -> cotangent in velocity space: (..., nf) -> (..., nv)."""
        k, m = self.n_periodic, self.n_plain
        qp = q[..., self.periodic_q]
        c_sin, c_cos = cotangent[..., :k], cotangent[..., k : 2 * k]
        out = cotangent.new_zeros(cotangent.shape[:-1] + (self.nv,))
        out[..., self.periodic_v] = torch.cos(qp) * c_sin - torch.sin(qp) * c_cos
        out[..., self.plain_v] = cotangent[..., 2 * k : 2 * k + m]
        if self.n_rot:
            G = cotangent[..., 2 * k + m :].unflatten(-1, (self.n_rot, 3, 3))
            out[..., self.rot_v] = unskew_of_rt(self._rotations(q), G)
        return out
