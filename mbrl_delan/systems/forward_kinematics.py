"""Batched torch forward kinematics of a MuJoCo kinematic tree (no simulator in the loop).

Rewards of the humanoid tasks need body and site poses for thousands of imagined states per
control step; this walks the body tree in torch the way MuJoCo's `mj_kinematics` does:

- a body with a free joint takes its position and (normalised) orientation from q;
- any other body starts at its parent's frame moved by its own offset (`body_pos`,
  `body_quat`), then applies its joints in order: a slide joint moves it along its axis by
  q - qpos0; a hinge rotates it about its axis by q - qpos0 and a ball by its (normalised)
  quaternion, both about the joint's anchor, which stays in place.

`dof_axes` also gives each DoF's world axis (and a point on it for a rotation), as MuJoCo's
`cdof` does: the point Jacobians of the contact model (`models/contact.py`) are built from them.

Quaternions are (w, x, y, z). `tests/test_forward_kinematics.py` compares with MuJoCo's
`xpos`, `xquat`, `site_xpos` and `mj_jac` on both humanoids.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import mujoco
import torch
from torch import Tensor, nn

FREE, BALL, SLIDE, HINGE = (
    int(mujoco.mjtJoint.mjJNT_FREE),
    int(mujoco.mjtJoint.mjJNT_BALL),
    int(mujoco.mjtJoint.mjJNT_SLIDE),
    int(mujoco.mjtJoint.mjJNT_HINGE),
)


# per joint kind, whether each of its DoFs rotates (else it translates)
ROTATES = {FREE: (False,) * 3 + (True,) * 3, BALL: (True,) * 3, SLIDE: (False,), HINGE: (True,)}


def quat_rotate(quat: Tensor, vec: Tensor) -> Tensor:
    """Rotate vectors by unit quaternions: (..., 4), (..., 3) -> (..., 3)."""
    w, xyz = quat[..., :1], quat[..., 1:]
    t = 2.0 * torch.linalg.cross(xyz, vec, dim=-1)
    return vec + w * t + torch.linalg.cross(xyz, t, dim=-1)


def _unit(quat: Tensor) -> Tensor:
    return quat / torch.linalg.vector_norm(quat, dim=-1, keepdim=True).clamp_min(1e-12)


@dataclass(frozen=True)
class Joint:
    """One joint of a body, as MuJoCo's model arrays give it."""

    kind: int  # FREE | BALL | SLIDE | HINGE
    qpos_adr: int  # first index in q
    axis: tuple[float, float, float]  # in the body frame (hinge, slide)
    anchor: tuple[float, float, float]  # `jnt_pos`, in the body frame
    qpos0: float  # reference position (hinge, slide)


@dataclass
class Poses:
    """World poses of every body and site."""

    xpos: Tensor  # (..., nbody, 3) body frame origins; body 0 is the world
    xmat: Tensor  # (..., nbody, 3, 3) body orientations (body axes to world)
    site_xpos: Tensor  # (..., nsite, 3)

    @property
    def xquat(self) -> Tensor:
        """The orientations as unit quaternions (w, x, y, z), w >= 0. (..., nbody, 4)"""
        return mat_to_quat(self.xmat)


@dataclass
class DofAxes:
    """Each DoF's motion in the world: a translation along `axis`, or a rotation about `axis`
    through `anchor` (`ForwardKinematics.rotational`)."""

    axis: Tensor  # (..., nv, 3) unit vectors
    anchor: Tensor  # (..., nv, 3)


Frames = tuple[Poses, DofAxes]  # what `ForwardKinematics.dof_axes` gives


class ForwardKinematics(nn.Module):
    """q (..., nq) -> `Poses`, for a tree given as plain arrays (see `from_mujoco`).

    Args:
        parent: parent body index of each body (body 0, the world, is its own parent).
        body_pos: (nbody, 3) offset of each body in its parent's frame.
        body_quat: (nbody, 4) orientation of each body in its parent's frame.
        joints: the joints of each body, in MuJoCo's order.
        site_body: body index of each site.
        site_pos: (nsite, 3) site offsets in their body's frame.
    """

    def __init__(
        self,
        parent: list[int],
        body_pos: Tensor,
        body_quat: Tensor,
        joints: list[list[Joint]],
        site_body: list[int],
        site_pos: Tensor,
    ) -> None:
        super().__init__()
        if not len(parent) == body_pos.shape[0] == body_quat.shape[0] == len(joints):
            raise ValueError("parent, body_pos, body_quat and joints must have one row per body")
        if any(p >= i for i, p in enumerate(parent) if i > 0):
            raise ValueError("bodies must come after their parent (MuJoCo's tree order)")
        self.parent, self.joints, self.site_body = parent, joints, site_body
        # per DoF, in MuJoCo's order: its body and whether it rotates (else it translates)
        self.dof_body = [b for b, js in enumerate(joints) for j in js for _ in ROTATES[j.kind]]
        self.rotational = [r for js in joints for j in js for r in ROTATES[j.kind]]
        self.register_buffer("body_pos", body_pos.double())
        self.register_buffer("body_quat", body_quat.double())
        self.register_buffer("site_pos", site_pos.double().reshape(-1, 3))
        # constant tensors on each (device, dtype) met: built once, so a call on a GPU copies
        # nothing from the host (a CUDA graph can capture it, see `placed`)
        self._placed: dict[tuple[torch.device, torch.dtype], _Placed] = {}

    @classmethod
    def from_mujoco(cls, model: mujoco.MjModel) -> ForwardKinematics:
        """The tree of a compiled MuJoCo model (mocap bodies are not supported)."""
        if model.nmocap:
            raise ValueError("forward kinematics does not support mocap bodies")
        joints = [
            [
                Joint(
                    kind=int(model.jnt_type[j]),
                    qpos_adr=int(model.jnt_qposadr[j]),
                    axis=tuple(float(x) for x in model.jnt_axis[j]),
                    anchor=tuple(float(x) for x in model.jnt_pos[j]),
                    qpos0=float(model.qpos0[model.jnt_qposadr[j]]),
                )
                for j in range(model.body_jntadr[b], model.body_jntadr[b] + model.body_jntnum[b])
            ]
            for b in range(model.nbody)
        ]
        return cls(
            parent=[int(p) for p in model.body_parentid],
            body_pos=torch.from_numpy(model.body_pos.copy()),
            body_quat=torch.from_numpy(model.body_quat.copy()),
            joints=joints,
            site_body=[int(b) for b in model.site_bodyid],
            site_pos=torch.from_numpy(model.site_pos.copy()),
        )

    def placed(self, like: Tensor) -> _Placed:
        """The tree's constants on `like`'s device and in its dtype, built on first use and
        again outside inference mode where they were built in it: a run resumed into planning
        (inference mode, possibly compiled) builds them there, and its fits use them under
        autograd, which cannot save inference tensors. Compiled code skips that check (Dynamo
        cannot trace `is_inference`, and a graph break there splits every planning step)."""
        key = (like.device, like.dtype)
        placed = self._placed.get(key)
        if placed is None or (not torch.compiler.is_compiling() and placed.body_mat.is_inference()
                              and not torch.is_inference_mode_enabled()):  # fmt: skip
            placed = self._placed[key] = _Placed.build(self, like)
        return placed

    def _apply(self, fn: Callable[..., Any], recurse: bool = True) -> ForwardKinematics:
        self._placed = {}  # a moved or cast module rebuilds its constants from its buffers
        return super()._apply(fn, recurse)

    def forward(self, q: Tensor, nbody: int | None = None) -> Poses:
        """Poses at positions q (..., nq), in q's dtype; with `nbody`, of the first `nbody`
        bodies only (and no sites): enough for a body and its ancestors, which come first."""
        return self._walk(q, None, nbody)

    def dof_axes(self, q: Tensor) -> tuple[Poses, DofAxes]:
        """Poses and each DoF's world axis at q (..., nq): MuJoCo's `xaxis` / `xanchor` for
        hinges and slides, the world axes for a free joint's translation, and the body's own
        axes for a free or ball joint's (body-frame) rotation."""
        axes: list[tuple[Tensor, Tensor]] = []
        poses = self._walk(q, axes)
        if not axes:
            return poses, DofAxes(q.new_zeros((*q.shape[:-1], 0, 3)), q.new_zeros(0, 3))
        axis, anchor = (torch.stack(t, dim=-2) for t in zip(*axes, strict=True))
        return poses, DofAxes(axis=axis, anchor=anchor)

    def _walk(
        self, q: Tensor, axes: list[tuple[Tensor, Tensor]] | None, nbody: int | None = None
    ) -> Poses:
        """Poses of the first `nbody` bodies (None: all, with the sites) at q (..., nq); each
        DoF's (axis, anchor) appended to `axes` unless None. Orientations are carried as
        rotation matrices: a hinge turns its body by exp(theta [a]x) = 1 + sin(theta) [a]x +
        (1 - cos(theta)) [a]x^2 with [a]x and its square constants of the tree."""
        batch, c = q.shape[:-1], self.placed(q)
        xpos = [q.new_zeros((*batch, 3))]
        xmat = [c.world_mat.expand(*batch, 3, 3)]
        for b in range(1, len(self.parent) if nbody is None else nbody):
            pos, mat = self._body(q, b, xpos, xmat, c, axes)
            xpos.append(pos)
            xmat.append(mat)
        xpos_t, xmat_t = torch.stack(xpos, dim=-2), torch.stack(xmat, dim=-3)
        sites = self._sites(xpos_t, xmat_t, c) if nbody is None else xpos_t[..., :0, :]
        return Poses(xpos=xpos_t, xmat=xmat_t, site_xpos=sites)

    def _body(
        self,
        q: Tensor,
        b: int,
        xpos: list[Tensor],
        xmat: list[Tensor],
        c: _Placed,
        axes: list[tuple[Tensor, Tensor]] | None = None,
    ) -> tuple[Tensor, Tensor]:
        """Position (..., 3) and orientation (..., 3, 3) of body b from its parent's."""
        joints = self.joints[b]
        if len(joints) == 1 and joints[0].kind == FREE:
            adr = joints[0].qpos_adr
            pos, mat = q[..., adr : adr + 3], quat_to_mat(q[..., adr + 3 : adr + 7])
            if axes is not None:
                world = c.world_mat.expand(*mat.shape)
                axes += [(world[..., k, :], pos) for k in range(3)]
                axes += [(mat[..., :, k], pos) for k in range(3)]
            return pos, mat
        p = self.parent[b]
        pos = xpos[p] + turn(xmat[p], c.body_pos[b])
        mat = _compose(xmat[p], c.body_mat[b])
        for joint, const in zip(joints, c.joints[b], strict=True):
            pos, mat = self._joint(q, joint, const, pos, mat, axes)
        return pos, mat

    @staticmethod
    def _joint(
        q: Tensor, joint: Joint, const: _JointConstants, pos: Tensor, mat: Tensor,
        axes: list[tuple[Tensor, Tensor]] | None,
    ) -> tuple[Tensor, Tensor]:  # fmt: skip
        """Apply one joint to the body frame (pos (..., 3), mat (..., 3, 3)); its DoFs'
        (axis, anchor) appended to `axes` unless None."""
        value = q[..., joint.qpos_adr : joint.qpos_adr + 1] - joint.qpos0  # (..., 1)
        if joint.kind == SLIDE:
            axis = turn(mat, const.axis)
            if axes is not None:
                axes.append((axis, pos + turn(mat, const.anchor)))
            return pos + axis * value, mat
        anchor = pos + turn(mat, const.anchor)  # stays in place
        if joint.kind == HINGE:
            if axes is not None:
                axes.append((turn(mat, const.axis), anchor))
            angle = value.unsqueeze(-1)  # (..., 1, 1)
            local = const.eye + torch.sin(angle) * const.skew
            local = local + (1.0 - torch.cos(angle)) * const.skew_sq
        elif joint.kind == BALL:
            local = quat_to_mat(q[..., joint.qpos_adr : joint.qpos_adr + 4])
        else:
            raise ValueError("a free joint must be its body's only joint")
        mat = _compose(mat, local)
        if axes is not None and joint.kind == BALL:
            axes += [(mat[..., :, k], anchor) for k in range(3)]
        return anchor - turn(mat, const.anchor), mat

    def _sites(self, xpos: Tensor, xmat: Tensor, c: _Placed) -> Tensor:
        """(..., nbody, 3), (..., nbody, 3, 3) -> site positions (..., nsite, 3)."""
        if not self.site_body:
            return xpos[..., :0, :]
        body_pos = xpos.index_select(-2, c.site_body)
        body_mat = xmat.index_select(-3, c.site_body)
        return body_pos + turn(body_mat, c.site_pos)


def turn(mat: Tensor, vec: Tensor) -> Tensor:
    """mat @ vec for rotations (..., 3, 3) and vectors (..., 3) or (3,), as three products of
    columns (elementwise: they fuse when compiled, and run eagerly several times faster than a
    reduction over a dimension of 3). -> (..., 3)"""
    return mat[..., 0] * vec[..., 0:1] + mat[..., 1] * vec[..., 1:2] + mat[..., 2] * vec[..., 2:3]


def _compose(a: Tensor, b: Tensor) -> Tensor:
    """a @ b for 3x3 matrices (..., 3, 3), as three outer products of a's columns and b's
    rows (elementwise, as `turn`). -> (..., 3, 3)"""
    column = lambda k: a[..., :, k : k + 1] * b[..., k : k + 1, :]  # noqa: E731
    return column(0) + column(1) + column(2)


def quat_to_mat(quat: Tensor) -> Tensor:
    """Rotation matrices of quaternions (w, x, y, z), normalised first. (..., 4) -> (..., 3, 3)"""
    w, x, y, z = _unit(quat).unbind(-1)
    rows = (
        (1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)),
        (2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)),
        (2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)),
    )
    return torch.stack([torch.stack(r, dim=-1) for r in rows], dim=-2)


def mat_to_quat(mat: Tensor) -> Tensor:
    """Unit quaternions (w, x, y, z) with w >= 0 of rotation matrices (..., 3, 3), from the
    largest of the four candidate pivots (Shepperd's method). -> (..., 4)"""
    m = mat
    trace = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    pivots = torch.stack([trace, m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]], -1)
    candidates = torch.stack([
        torch.stack([1 + trace, m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0],
                     m[..., 1, 0] - m[..., 0, 1]], -1),
        torch.stack([m[..., 2, 1] - m[..., 1, 2], 1 + 2 * m[..., 0, 0] - trace,
                     m[..., 0, 1] + m[..., 1, 0], m[..., 0, 2] + m[..., 2, 0]], -1),
        torch.stack([m[..., 0, 2] - m[..., 2, 0], m[..., 0, 1] + m[..., 1, 0],
                     1 + 2 * m[..., 1, 1] - trace, m[..., 1, 2] + m[..., 2, 1]], -1),
        torch.stack([m[..., 1, 0] - m[..., 0, 1], m[..., 0, 2] + m[..., 2, 0],
                     m[..., 1, 2] + m[..., 2, 1], 1 + 2 * m[..., 2, 2] - trace], -1),
    ], -2)  # fmt: skip
    best = pivots.argmax(-1, keepdim=True)  # (..., 1)
    quat = candidates.gather(-2, best.unsqueeze(-1).expand(*best.shape, 4)).squeeze(-2)
    quat = _unit(quat)
    return torch.where(quat[..., :1] < 0, -quat, quat)


@dataclass(frozen=True)
class _JointConstants:
    """One joint's constants on a device: its axis and anchor (3,) in the body frame, the
    cross-product matrix [a]x of its axis and its square (3, 3), and the identity."""

    axis: Tensor
    anchor: Tensor
    skew: Tensor
    skew_sq: Tensor
    eye: Tensor


@dataclass(frozen=True)
class _Placed:
    """`ForwardKinematics`' constants on one device, in one dtype."""

    body_pos: Tensor  # (nbody, 3)
    body_mat: Tensor  # (nbody, 3, 3)
    site_pos: Tensor  # (nsite, 3)
    site_body: Tensor  # (nsite,) int64
    world_mat: Tensor  # (3, 3) the identity
    joints: list[list[_JointConstants]]  # per body, per joint

    @classmethod
    def build(cls, fk: ForwardKinematics, like: Tensor) -> _Placed:
        def vec(values: tuple[float, ...]) -> Tensor:
            return torch.tensor(values, dtype=like.dtype, device=like.device)

        eye = torch.eye(3, dtype=like.dtype, device=like.device)

        def constants(joint: Joint) -> _JointConstants:
            axis = vec(joint.axis)
            skew = torch.linalg.cross(axis.expand(3, 3), eye, dim=-1).transpose(0, 1)
            return _JointConstants(axis, vec(joint.anchor), skew, skew @ skew, eye)

        return cls(
            body_pos=fk.body_pos.to(like),
            body_mat=quat_to_mat(fk.body_quat.to(like)),
            site_pos=fk.site_pos.to(like),
            site_body=torch.tensor(fk.site_body, dtype=torch.long, device=like.device),
            world_mat=eye,
            joints=[[constants(j) for j in joints] for joints in fk.joints],
        )
