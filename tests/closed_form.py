"""Closed-form rigid-body dynamics of pendulum.xml and arm2.xml (test helper).

Angles hang down at 0 and are relative (elbow measured from link 1); MuJoCo's sign
conventions: tau = M(q) qdd + c(q, qd) + g(q) with c + g = qfrc_bias. Inputs are torch
tensors batched over leading dims; use float64 for comparisons with MuJoCo.
"""

from __future__ import annotations

import torch
from torch import Tensor

from mbrl_delan.tasks.arm_reach import ARM2_LINK_LENGTHS, ARM2_MASSES, GRAVITY
from mbrl_delan.tasks.pendulum import PENDULUM_INERTIA, PENDULUM_LENGTH, PENDULUM_MASS


def _arm2_params() -> tuple[float, float, float, float, float, float, float, float]:
    """(m1, m2, l1, lc1, lc2, I1, I2, g): uniform links, COM at mid-link, I = m l^2 / 12."""
    (l1, l2), (m1, m2) = ARM2_LINK_LENGTHS, ARM2_MASSES
    return m1, m2, l1, l1 / 2, l2 / 2, m1 * l1**2 / 12, m2 * l2**2 / 12, GRAVITY


def pendulum_mass_matrix(q: Tensor) -> Tensor:
    """(..., 1) -> (..., 1, 1): I + m l^2, constant."""
    value = PENDULUM_INERTIA + PENDULUM_MASS * PENDULUM_LENGTH**2
    return torch.full((*q.shape[:-1], 1, 1), value, dtype=q.dtype, device=q.device)


def pendulum_gravity(q: Tensor) -> Tensor:
    """(..., 1) -> (..., 1): dV/dq with V = -m g l cos q."""
    return PENDULUM_MASS * GRAVITY * PENDULUM_LENGTH * torch.sin(q)


def arm2_mass_matrix(q: Tensor) -> Tensor:
    """(..., 2) -> (..., 2, 2)."""
    m1, m2, l1, lc1, lc2, i1, i2, _ = _arm2_params()
    c2 = torch.cos(q[..., 1])
    m22 = torch.full_like(c2, i2 + m2 * lc2**2)
    m12 = i2 + m2 * (lc2**2 + l1 * lc2 * c2)
    m11 = i1 + i2 + m1 * lc1**2 + m2 * (l1**2 + lc2**2 + 2 * l1 * lc2 * c2)
    row1 = torch.stack((m11, m12), dim=-1)
    row2 = torch.stack((m12, m22), dim=-1)
    return torch.stack((row1, row2), dim=-2)


def arm2_gravity(q: Tensor) -> Tensor:
    """(..., 2) -> (..., 2): dV/dq with V = -g (m1 lc1 cos q1 + m2 (l1 cos q1 + lc2 cos q12))."""
    m1, m2, l1, lc1, lc2, _, _, g = _arm2_params()
    s1, s12 = torch.sin(q[..., 0]), torch.sin(q[..., 0] + q[..., 1])
    g1 = g * (m1 * lc1 * s1 + m2 * (l1 * s1 + lc2 * s12))
    g2 = g * m2 * lc2 * s12
    return torch.stack((g1, g2), dim=-1)


def arm2_coriolis(q: Tensor, qd: Tensor) -> Tensor:
    """(..., 2), (..., 2) -> (..., 2): Coriolis and centrifugal forces c(q, qd)."""
    m1, m2, l1, lc1, lc2, _, _, _ = _arm2_params()
    h = m2 * l1 * lc2 * torch.sin(q[..., 1])
    qd1, qd2 = qd[..., 0], qd[..., 1]
    return torch.stack((-h * (2 * qd1 * qd2 + qd2.square()), h * qd1.square()), dim=-1)


def pendulum_potential(q: Tensor) -> Tensor:
    """(..., 1) -> (...): V = -m g l cos q (zero at the pivot's height)."""
    return -PENDULUM_MASS * GRAVITY * PENDULUM_LENGTH * torch.cos(q[..., 0])


def arm2_potential(q: Tensor) -> Tensor:
    """(..., 2) -> (...): V = -g (m1 lc1 cos q1 + m2 (l1 cos q1 + lc2 cos q12))."""
    m1, m2, l1, lc1, lc2, _, _, g = _arm2_params()
    c1, c12 = torch.cos(q[..., 0]), torch.cos(q[..., 0] + q[..., 1])
    return -g * (m1 * lc1 * c1 + m2 * (l1 * c1 + lc2 * c12))
