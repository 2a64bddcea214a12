"""Torch versions of MuJoCo's mj_integratePos / mj_differentiatePos.

All position arithmetic on q goes through these two functions.

Conventions follow MuJoCo exactly:

- hinge and slide joints: one coordinate, q' = q + v dt;
- free joints: world-frame translation (3 coordinates, added like slides) followed by a
  quaternion (w, x, y, z) whose angular velocity is expressed in the *body* frame;
- ball joints: a quaternion with body-frame angular velocity.

Integration rotates by the axis-angle vector w dt applied on the right,
``quat' = quat * exp(w dt / 2)``, after normalising ``quat`` (as ``mju_quatIntegrate``).
Differentiation normalises both quaternions and takes the logarithm of
``conj(quat1) * quat2`` with the rotation angle wrapped to (-pi, pi] (as ``mju_subQuat``).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import torch
from torch import Tensor

from mbrl_delan.systems.system import BALL, FREE, JointLayout

_TINY = 1e-300  # below this a vector norm is treated as zero (keeps gradients finite)


@dataclass(frozen=True)
class _Index:
    """Index plan of a layout: which coordinates are added linearly, which are quaternions."""

    lin_q: tuple[int, ...]  # qpos indices updated as q + v dt (hinge, slide, free translation)
    lin_v: tuple[int, ...]  # matching qvel indices
    quat_q: tuple[tuple[int, int, int, int], ...]  # qpos indices of each quaternion (w, x, y, z)
    rot_v: tuple[tuple[int, int, int], ...]  # qvel indices of each body-frame angular velocity

    def q_order(self) -> list[int]:
        """qpos indices in the order [lin, quats flattened]."""
        return list(self.lin_q) + [i for quat in self.quat_q for i in quat]

    def v_order(self) -> list[int]:
        """qvel indices in the order [lin, rots flattened]."""
        return list(self.lin_v) + [i for rot in self.rot_v for i in rot]


@functools.lru_cache(maxsize=64)
def _index_plan(layout: JointLayout) -> _Index:
    lin_q: list[int] = []
    lin_v: list[int] = []
    quat_q: list[tuple[int, int, int, int]] = []
    rot_v: list[tuple[int, int, int]] = []
    for jtype, qa, va in zip(layout.types, layout.qpos_adr, layout.dof_adr, strict=True):
        if jtype == FREE:
            lin_q += [qa, qa + 1, qa + 2]
            lin_v += [va, va + 1, va + 2]
            qa, va = qa + 3, va + 3
        if jtype in (FREE, BALL):
            quat_q.append((qa, qa + 1, qa + 2, qa + 3))
            rot_v.append((va, va + 1, va + 2))
        else:
            lin_q.append(qa)
            lin_v.append(va)
    return _Index(tuple(lin_q), tuple(lin_v), tuple(quat_q), tuple(rot_v))


@functools.lru_cache(maxsize=64)
def _index_tensors(
    layout: JointLayout, device: torch.device
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """(lin_q, lin_v, quat_q (K, 4), rot_v (K, 3), inverse q order, inverse v order) on device.

    Built as normal tensors even when first called under `torch.inference_mode` (planning):
    the cached indices are later used in autograd (fitting), which cannot save inference
    tensors for backward.
    """
    with torch.inference_mode(False):
        return _build_index_tensors(layout, device)


def _build_index_tensors(
    layout: JointLayout, device: torch.device
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    plan = _index_plan(layout)

    def idx(values: object) -> Tensor:
        return torch.as_tensor(values, dtype=torch.long, device=device)

    inv_q = torch.argsort(idx(plan.q_order()))
    inv_v = torch.argsort(idx(plan.v_order()))
    quat_q = idx(plan.quat_q).reshape(-1, 4)
    rot_v = idx(plan.rot_v).reshape(-1, 3)
    return idx(plan.lin_q), idx(plan.lin_v), quat_q, rot_v, inv_q, inv_v


def quat_mul(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product of quaternions (w, x, y, z). (..., 4), (..., 4) -> (..., 4)."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        (
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ),
        dim=-1,
    )


def quat_conj(q: Tensor) -> Tensor:
    """Conjugate (inverse of a unit quaternion). (..., 4) -> (..., 4)."""
    return torch.cat((q[..., :1], -q[..., 1:]), dim=-1)


def quat_exp(rotvec: Tensor) -> Tensor:
    """Unit quaternion of an axis-angle vector (angle = norm). (..., 3) -> (..., 4)."""
    angle = torch.linalg.vector_norm(rotvec, dim=-1, keepdim=True)  # (..., 1)
    small = angle < 1e-8
    safe = torch.where(small, torch.ones_like(angle), angle)
    # sin(a/2)/a, with its Taylor expansion near zero
    coef = torch.where(small, 0.5 - angle.square() / 48.0, torch.sin(0.5 * safe) / safe)
    return torch.cat((torch.cos(0.5 * angle), rotvec * coef), dim=-1)


def quat_log(quat: Tensor) -> Tensor:
    """Axis-angle vector of a unit quaternion, angle wrapped to [-pi, pi]. (..., 4) -> (..., 3).

    Matches ``mju_quat2Vel(res, quat, 1)``: q and -q give the same rotation vector.
    """
    quat = torch.where(quat[..., :1] < 0, -quat, quat)  # w >= 0: the short way round
    w, xyz = quat[..., :1], quat[..., 1:]
    s = torch.linalg.vector_norm(xyz, dim=-1, keepdim=True)  # sin(angle / 2)
    small = s < 1e-8
    safe = torch.where(small, torch.ones_like(s), s)
    # angle / sin(angle / 2) = 2 atan2(s, w) / s  ->  2 / w as s -> 0
    coef = torch.where(small, 2.0 / w, 2.0 * torch.atan2(s, w) / safe)
    return xyz * coef


def _normalize(quat: Tensor) -> Tensor:
    return quat / torch.linalg.vector_norm(quat, dim=-1, keepdim=True).clamp_min(_TINY)


def integrate_pos(layout: JointLayout, q: Tensor, qd: Tensor, dt: float | Tensor) -> Tensor:
    """q' = q (+) qd * dt, batched over leading dims. q: (..., nq), qd: (..., nv) -> (..., nq).

    `dt` is a float or a tensor broadcastable to (..., 1).
    """
    if layout.only_scalar_joints:
        return q + qd * dt
    lin_q, lin_v, quat_q, rot_v, inv_q, _ = _index_tensors(layout, q.device)
    step = qd * dt  # (..., nv)
    batch = torch.broadcast_shapes(q.shape[:-1], step.shape[:-1])
    q, step = q.expand(*batch, q.shape[-1]), step.expand(*batch, step.shape[-1])
    lin = q[..., lin_q] + step[..., lin_v]  # (..., n_lin)
    quats = _normalize(q[..., quat_q])  # (..., K, 4)
    quats = quat_mul(quats, quat_exp(step[..., rot_v]))  # (..., K, 4)
    out = torch.cat((lin, quats.flatten(-2)), dim=-1)  # (..., nq) in plan order
    return out[..., inv_q]


def differentiate_pos(layout: JointLayout, q1: Tensor, q2: Tensor, dt: float | Tensor) -> Tensor:
    """Velocity qd with q2 = q1 (+) qd * dt. q1, q2: (..., nq) -> (..., nv).

    `dt` is a float or a tensor broadcastable to (..., 1).
    """
    if layout.only_scalar_joints:
        return (q2 - q1) / dt
    lin_q, _, quat_q, _, _, inv_v = _index_tensors(layout, q1.device)
    lin = q2[..., lin_q] - q1[..., lin_q]  # (..., n_lin)
    rel = quat_mul(quat_conj(_normalize(q1[..., quat_q])), _normalize(q2[..., quat_q]))
    rot = quat_log(rel)  # (..., K, 3)
    out = torch.cat((lin, rot.flatten(-2)), dim=-1)  # (..., nv) in plan order
    return out[..., inv_v] / dt
