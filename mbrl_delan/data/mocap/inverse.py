"""Generalized forces of retargeted motion by MuJoCo's inverse dynamics (``mj_inverse``).

Contacts and joint limits are off: every CMU clip leaves some joint ranges, and the ground
reaction is not modelled. What the root needs to follow the motion, which in reality the
ground (and nothing inside the body) provides, is the root residual: the 6 generalized forces
on the free joint. The joint torques are the forces on the 56 hinges.

``tau`` is MuJoCo's ``qfrc_inverse``: the ``qfrc_applied`` that makes ``mj_forward`` (with the
same options) return ``qacc = qdd``; in the model's terms
``tau = M(q) qdd + qfrc_bias(q, qd) - qfrc_passive(q, qd)``. With ``passive=True`` (default)
the MJCF's joint springs and dampers stay in the model, so tau holds the forces that cancel
them; ``passive=False`` switches them off (``mjDSBL_SPRING | mjDSBL_DAMPER``) and tau is the
rigid-body inverse dynamics alone.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np
import torch
from torch import Tensor

from mbrl_delan.systems.system import BALL, FREE

F64 = torch.float64
_OFF = int(mujoco.mjtDisableBit.mjDSBL_CONTACT) | int(mujoco.mjtDisableBit.mjDSBL_LIMIT)
_PASSIVE = int(mujoco.mjtDisableBit.mjDSBL_SPRING) | int(mujoco.mjtDisableBit.mjDSBL_DAMPER)


@dataclass
class InverseDynamics:
    """Generalized forces along a motion, float64."""

    tau: Tensor  # (T, nv): qfrc_inverse, joint torques and root residual in their dof slots
    joint_tau: Tensor  # (T, nv - 6): the hinge torques, tau[:, joint_dofs]
    root_residual: Tensor  # (T, 6): force (world frame) and torque (body frame) on the root
    joint_dofs: tuple[int, ...]  # dof indices of joint_tau in tau
    root_dofs: tuple[int, ...]  # dof indices of root_residual in tau


def dynamics_model(model: mujoco.MjModel, passive: bool = True) -> mujoco.MjModel:
    """A copy of ``model`` with contacts and limits off (and springs/dampers if not passive)."""
    out = copy_model(model)
    out.opt.disableflags |= _OFF | (0 if passive else _PASSIVE)
    return out


def copy_model(model: mujoco.MjModel) -> mujoco.MjModel:
    """An independent copy of an MjModel."""
    return model.__copy__()


def random_poses(model: mujoco.MjModel, n: int, seed: int = 0) -> Tensor:
    """Poses spread over the model's whole configuration space, far from any clip: a free
    root anywhere near the origin (unit normal position) with a uniform orientation, ball
    joints uniform, hinges and slides uniform in their range (unlimited: [-pi, pi]).
    float64 (n, nq)."""
    g = torch.Generator().manual_seed(seed)
    q = torch.zeros(n, model.nq, dtype=torch.float64)
    for j in range(model.njnt):
        adr, kind = int(model.jnt_qposadr[j]), int(model.jnt_type[j])
        if kind in (FREE, BALL):
            if kind == FREE:
                q[:, adr : adr + 3] = torch.randn(n, 3, generator=g, dtype=torch.float64)
                adr += 3
            quat = torch.randn(n, 4, generator=g, dtype=torch.float64)
            q[:, adr : adr + 4] = quat / quat.norm(dim=1, keepdim=True)
            continue
        low, high = model.jnt_range[j] if model.jnt_limited[j] else (-np.pi, np.pi)
        q[:, adr] = low + (high - low) * torch.rand(n, generator=g, dtype=torch.float64)
    return q


def root_dofs(model: mujoco.MjModel) -> tuple[int, ...]:
    """The 6 dof indices of the model's free joint (empty if it has none)."""
    out: list[int] = []
    for j in range(model.njnt):
        if model.jnt_type[j] == FREE:
            start = int(model.jnt_dofadr[j])
            out += range(start, start + 6)
    return tuple(out)


def inverse_dynamics(
    model: mujoco.MjModel, q: Tensor, qd: Tensor, qdd: Tensor, passive: bool = True
) -> InverseDynamics:
    """``mj_inverse`` at every sample, contacts and limits off.

    Args:
        model: the model the motion was retargeted onto (not modified).
        q: (T, nq), qd: (T, nv), qdd: (T, nv).
        passive: keep the MJCF's joint springs and dampers (see module docstring).
    """
    n = q.shape[0]
    if qd.shape[0] != n or qdd.shape[0] != n:
        raise ValueError(f"q, qd, qdd need the same length, got {n}, {qd.shape[0]}, {qdd.shape[0]}")
    m = dynamics_model(model, passive)
    data = mujoco.MjData(m)
    q_np, qd_np, qdd_np = (x.detach().cpu().to(F64).numpy() for x in (q, qd, qdd))
    tau = np.empty((n, m.nv))
    for i in range(n):
        data.qpos[:] = q_np[i]
        data.qvel[:] = qd_np[i]
        data.qacc[:] = qdd_np[i]
        mujoco.mj_inverse(m, data)
        tau[i] = data.qfrc_inverse
    root = root_dofs(m)
    joints = tuple(i for i in range(m.nv) if i not in set(root))
    tau_t = torch.from_numpy(tau)
    return InverseDynamics(
        tau=tau_t,
        joint_tau=tau_t[:, list(joints)].clone(),
        root_residual=tau_t[:, list(root)].clone(),
        joint_dofs=joints,
        root_dofs=root,
    )


def forward_accelerations(
    model: mujoco.MjModel, q: Tensor, qd: Tensor, tau: Tensor, passive: bool = True
) -> Tensor:
    """``mj_forward``'s qacc with ``qfrc_applied = tau``, same options as `inverse_dynamics`.

    q: (T, nq), qd: (T, nv), tau: (T, nv) -> qacc (T, nv). The check of a round trip.
    """
    m = dynamics_model(model, passive)
    data = mujoco.MjData(m)
    out = np.empty((q.shape[0], m.nv))
    for i, (qi, vi, fi) in enumerate(zip(q.numpy(), qd.numpy(), tau.numpy(), strict=True)):
        data.qpos[:], data.qvel[:], data.qfrc_applied[:] = qi, vi, fi
        mujoco.mj_forward(m, data)
        out[i] = data.qacc
    return torch.from_numpy(out)
