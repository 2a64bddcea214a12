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
class _Segment:
    """A run of coordinates in qpos order: `quat` a quaternion (qpos q0:q1, its body-frame
    angular velocity qvel v0:v1), else coordinates added linearly (qpos q0:q1, qvel v0:v1)."""

    quat: bool
    q0: int
    q1: int
    v0: int
    v1: int


@functools.lru_cache(maxsize=64)
def _segments(layout: JointLayout) -> tuple[_Segment, ...]:
    """The layout's coordinates as runs of Python slices, in qpos (and qvel) order: the
    arithmetic below slices and concatenates, so it builds no index tensor (a compiled loop
    over the horizon cannot declare tensors made while tracing)."""
    runs: list[_Segment] = []

    def linear(qa: int, va: int, n: int) -> None:
        last = runs[-1] if runs else None
        if last is not None and not last.quat and (last.q1, last.v1) == (qa, va):
            runs[-1] = _Segment(False, last.q0, qa + n, last.v0, va + n)
        else:
            runs.append(_Segment(False, qa, qa + n, va, va + n))

    for jtype, qa, va in zip(layout.types, layout.qpos_adr, layout.dof_adr, strict=True):
        if jtype == FREE:
            linear(qa, va, 3)
            qa, va = qa + 3, va + 3
        if jtype in (FREE, BALL):
            runs.append(_Segment(True, qa, qa + 4, va, va + 3))
        else:
            linear(qa, va, 1)
    starts = [(seg.q0, seg.v0) for seg in runs]
    ends = [(0, 0)] + [(seg.q1, seg.v1) for seg in runs[:-1]]
    if starts != ends:
        raise ValueError(f"joint coordinates out of MuJoCo's order: {layout}")
    return tuple(runs)


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
    step = qd * dt  # (..., nv)
    batch = torch.broadcast_shapes(q.shape[:-1], step.shape[:-1])
    q, step = q.expand(*batch, q.shape[-1]), step.expand(*batch, step.shape[-1])
    parts = []
    for seg in _segments(layout):
        coords, move = q[..., seg.q0 : seg.q1], step[..., seg.v0 : seg.v1]
        parts.append(quat_mul(_normalize(coords), quat_exp(move)) if seg.quat else coords + move)
    return torch.cat(parts, dim=-1)


def differentiate_pos(layout: JointLayout, q1: Tensor, q2: Tensor, dt: float | Tensor) -> Tensor:
    """Velocity qd with q2 = q1 (+) qd * dt. q1, q2: (..., nq) -> (..., nv).

    `dt` is a float or a tensor broadcastable to (..., 1).
    """
    if layout.only_scalar_joints:
        return (q2 - q1) / dt
    parts = []
    for seg in _segments(layout):
        a, b = q1[..., seg.q0 : seg.q1], q2[..., seg.q0 : seg.q1]
        parts.append(quat_log(quat_mul(quat_conj(_normalize(a)), _normalize(b))) if seg.quat
                     else b - a)  # fmt: skip
    return torch.cat(parts, dim=-1) / dt
