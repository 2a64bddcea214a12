"""Contacts with structure: forces at points of the body tree, mapped by the contact Jacobian.

The points are the sphere centres and capsule end points of every geom that can touch the
floor plane, each with its radius (`ContactPoints.from_mujoco`). At a state (q, qd):

- p_i (..., P, 3) from the torch forward kinematics and v_i = J_i(q) qd, J_i (3, nv) the
  point's Jacobian: the world axes of the DoFs above its body (`ForwardKinematics.dof_axes`);
- penetration d_i = max(floor + r_i - p_iz, 0) and normal speed v_n = v_iz;
- normal force (Hunt-Crossley) f_n = W k (d / delta)^e max(1 - c v_n, 0): zero without
  contact, never negative, growing with d (e >= 1), larger while the point approaches
  (v_n < 0) than while it leaves, so every bounce loses energy. W is the body's weight and
  delta = 1 cm, so k is unitless;
- friction f_t = -mu f_n v_t / sqrt(|v_t|^2 + eps^2), v_t the tangential velocity: against
  the slip and strictly inside the cone |f_t| <= mu f_n;
- the generalized force tau = sum_i J_i^T f_i (..., nv).

k, e, c and mu are learned, positive by construction, and shared by every point.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import mujoco
import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from mbrl_delan.systems.forward_kinematics import ForwardKinematics, quat_rotate

PENETRATION_UNIT = 0.01  # delta, m: k is the force per point, in body weights, at 1 cm
SLIP_SPEED = 0.01  # eps, m/s: below this slip the friction force fades linearly to zero


def _inverse_softplus(y: float) -> float:
    return math.log(math.expm1(y))


@dataclass(frozen=True)
class ContactPoints:
    """Where a body tree can touch the floor: points fixed in bodies, with a radius each."""

    body: tuple[int, ...]  # body of each point
    offset: tuple[tuple[float, float, float], ...]  # in the body's frame, m
    radius: tuple[float, ...]  # m
    floor: float  # height of the floor plane, m
    weight: float  # the whole body's weight, N (total mass x |gravity|)

    @classmethod
    def from_mujoco(cls, model: mujoco.MjModel) -> ContactPoints:
        """Sphere centres and capsule ends of the geoms that collide with the model's plane
        (the highest one if there are several; needs one)."""
        plane = mujoco.mjtGeom.mjGEOM_PLANE
        planes = [g for g in range(model.ngeom) if model.geom_type[g] == plane]
        if not planes:
            raise ValueError("a contact model needs a floor: the MuJoCo model has no plane geom")
        floor = max(planes, key=lambda g: model.geom_pos[g, 2])
        body, offset, radius = [], [], []
        for g in range(model.ngeom):
            if model.geom_bodyid[g] == 0 or not _collides(model, g, floor):
                continue
            ends = _geom_points(model, g)
            body += [int(model.geom_bodyid[g])] * len(ends)
            offset += [tuple(float(x) for x in p) for p in ends]
            radius += [float(model.geom_size[g, 0])] * len(ends)
        if not body:
            raise ValueError("no sphere or capsule geom of the MuJoCo model touches its floor")
        mass = float(model.body_mass.sum())
        weight = mass * float(np.linalg.norm(model.opt.gravity))
        return cls(tuple(body), tuple(offset), tuple(radius), float(model.geom_pos[floor, 2]),
                   weight)  # fmt: skip


def _collides(model: mujoco.MjModel, g: int, other: int) -> bool:
    """MuJoCo's contype / conaffinity filter between geoms g and other."""
    return bool(
        (model.geom_contype[g] & model.geom_conaffinity[other])
        or (model.geom_contype[other] & model.geom_conaffinity[g])
    )


def _geom_points(model: mujoco.MjModel, g: int) -> list[np.ndarray]:
    """A sphere's centre or a capsule's two end points in its body's frame (others: none)."""
    pos, quat = model.geom_pos[g], model.geom_quat[g]
    if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_SPHERE:
        return [pos.copy()]
    if model.geom_type[g] != mujoco.mjtGeom.mjGEOM_CAPSULE:
        return []
    ends = []
    for sign in (-1.0, 1.0):
        local, out = np.array([0.0, 0.0, sign * model.geom_size[g, 1]]), np.zeros(3)
        mujoco.mju_rotVecQuat(out, local, quat)
        ends.append(pos + out)
    return ends


@dataclass
class ContactState:
    """The contact points at one state and what acts on them."""

    position: Tensor  # (..., P, 3) world
    velocity: Tensor  # (..., P, 3) world
    force: Tensor  # (..., P, 3) world, on the body


class ContactModel(nn.Module):
    """Generalized contact forces of a body tree on a floor: (q, qd) -> tau (..., nv).

    Args:
        fk: the tree's forward kinematics (`ForwardKinematics.from_mujoco`).
        points: the contact points (`ContactPoints.from_mujoco`).
    """

    def __init__(self, fk: ForwardKinematics, points: ContactPoints) -> None:
        super().__init__()
        if len(points.body) != len(points.offset) or len(points.body) != len(points.radius):
            raise ValueError("contact points need a body, an offset and a radius each")
        self.fk, self.points = fk, points
        self.register_buffer("offset", torch.tensor(points.offset, dtype=torch.float64))
        self.register_buffer("radius", torch.tensor(points.radius, dtype=torch.float64))
        self.register_buffer("body", torch.tensor(points.body, dtype=torch.long))
        below = [_subtree_mask(fk.parent, b) for b in points.body]  # (P, nbody)
        mask = [[below[i][b] for b in fk.dof_body] for i in range(len(points.body))]
        self.register_buffer("moves", torch.tensor(mask, dtype=torch.float64))  # (P, nv)
        self.register_buffer("rotational", torch.tensor(fk.rotational))  # (nv,)
        self.log_stiffness = nn.Parameter(torch.tensor(math.log(0.5)))  # k = 0.5
        self.raw_exponent = nn.Parameter(torch.tensor(_inverse_softplus(0.5)))  # e = 1.5
        self.raw_damping = nn.Parameter(torch.tensor(_inverse_softplus(1.0)))  # c = 1 s/m
        self.raw_friction = nn.Parameter(torch.tensor(_inverse_softplus(1.0)))  # mu = 1

    @classmethod
    def from_mujoco(cls, model: mujoco.MjModel) -> ContactModel:
        return cls(ForwardKinematics.from_mujoco(model), ContactPoints.from_mujoco(model))

    def law(self) -> dict[str, Tensor]:
        """The learned constants: stiffness k, exponent e, damping c (s/m), friction mu."""
        return dict(
            stiffness=self.log_stiffness.exp(),
            exponent=1.0 + F.softplus(self.raw_exponent),
            damping=F.softplus(self.raw_damping),
            friction=F.softplus(self.raw_friction),
        )

    def forward(self, q: Tensor, qd: Tensor) -> Tensor:
        """The generalized contact force: (..., nq), (..., nv) -> (..., nv)."""
        position, jacobian = self.kinematics(q)
        velocity = torch.einsum("...pkv,...v->...pk", jacobian, qd)  # (..., P, 3)
        force = self.point_forces(position, velocity)
        return torch.einsum("...pkv,...pk->...v", jacobian, force)

    def contact_state(self, q: Tensor, qd: Tensor) -> ContactState:
        """The points, their velocities and the forces on them at (q, qd)."""
        position, jacobian = self.kinematics(q)
        velocity = torch.einsum("...pkv,...v->...pk", jacobian, qd)
        return ContactState(position, velocity, self.point_forces(position, velocity))

    def kinematics(self, q: Tensor) -> tuple[Tensor, Tensor]:
        """The points (..., P, 3) and their Jacobians (..., P, 3, nv) at q (..., nq):
        dp_i/dt = J_i qd."""
        poses, axes = self.fk.dof_axes(q)
        pos = poses.xpos.index_select(-2, self.body)
        quat = poses.xquat.index_select(-2, self.body)
        position = pos + quat_rotate(quat, self.offset.to(q).expand_as(pos))  # (..., P, 3)
        lever = position.unsqueeze(-2) - axes.anchor.unsqueeze(-3)  # (..., P, nv, 3)
        axis = axes.axis.unsqueeze(-3).expand_as(lever)
        turn = torch.linalg.cross(axis, lever, dim=-1)
        columns = torch.where(self.rotational.unsqueeze(-1), turn, axis)  # (..., P, nv, 3)
        return position, (columns * self.moves.to(q).unsqueeze(-1)).transpose(-1, -2)

    def point_forces(self, position: Tensor, velocity: Tensor) -> Tensor:
        """Forces (..., P, 3) on points at `position` moving at `velocity` (..., P, 3)."""
        law = {name: value.to(position) for name, value in self.law().items()}
        depth = torch.clamp(self.points.floor + self.radius.to(position) - position[..., 2], 0)
        ratio = torch.clamp(depth / PENETRATION_UNIT, min=1e-12)  # log(0): no NaN gradient
        spring = torch.where(
            depth > 0, self.points.weight * law["stiffness"] * ratio.pow(law["exponent"]), 0.0
        )
        normal = spring * torch.clamp(1.0 - law["damping"] * velocity[..., 2], min=0.0)
        slip = velocity[..., :2]  # (..., P, 2)
        speed = torch.sqrt(slip.square().sum(-1, keepdim=True) + SLIP_SPEED**2)
        tangential = -law["friction"] * normal.unsqueeze(-1) * slip / speed
        return torch.cat([tangential, normal.unsqueeze(-1)], dim=-1)


def _subtree_mask(parent: list[int], body: int) -> list[bool]:
    """Per body b: is `body` b itself or below it in the tree (b an ancestor of `body`)."""
    ancestors = set()
    while body > 0:
        ancestors.add(body)
        body = parent[body]
    return [b in ancestors for b in range(len(parent))]
