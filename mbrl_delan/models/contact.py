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

k, e, c and mu are learned, positive by construction, one set per contact group
(`ContactPoints.groups`: each leaf body of the tree its own, such as each foot and each hand;
the bodies just above them, ``limbs``; the rest, ``trunk``). They start from physics
(`ContactLaw.from_physics`): friction 1, a stiffness at which two points hold the body's
weight at `HOLD_DEPTH`, and the damping that makes that stance critically damped.

Stepped explicitly, a stiff law needs small steps. `implicit_acceleration` instead takes the
contact's damping and stiffness at the end of the step (a linearly implicit step at the
velocity level with the model's own M: M + dt J^T K J), which stays stable and gains no energy
at any stiffness, and is differentiable for the fit.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace

import mujoco
import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from mbrl_delan.systems.forward_kinematics import ForwardKinematics, Frames

log = logging.getLogger(__name__)

PENETRATION_UNIT = 0.01  # delta, m: k is the force per point, in body weights, at 1 cm
SLIP_SPEED = 0.01  # eps, m/s: below this slip the friction force fades linearly to zero
HOLD_DEPTH = 0.003  # m: the start's stiffness holds the body's weight on two points this deep
START_EXPONENT = 1.5  # e at the start
GRAVITY = 9.81  # m/s^2, for the start's damping
TRUNK, LIMBS = "trunk", "limbs"  # the groups of points on inner bodies
MAX_DEPTH = 0.05  # m: the law saturates at this penetration (states far off any data)


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
    group: tuple[int, ...] = ()  # contact group of each point (index into `groups`)
    groups: tuple[str, ...] = ()  # group names

    def __post_init__(self) -> None:
        if not self.group:  # one group for every point
            object.__setattr__(self, "group", (0,) * len(self.body))
            object.__setattr__(self, "groups", (TRUNK,))

    @classmethod
    def from_mujoco(cls, model: mujoco.MjModel) -> ContactPoints:
        """Sphere centres and capsule ends of the geoms that collide with the model's plane
        (the highest one if there are several; needs one); each radius is the geom's plus the
        pair's margin less its gap, where MuJoCo's contact starts to act."""
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
            # MuJoCo's contact acts from `margin - gap` (of the pair) before the surfaces touch
            reach = model.geom_margin[g] + model.geom_margin[floor]
            reach -= model.geom_gap[g] + model.geom_gap[floor]
            radius += [float(model.geom_size[g, 0] + reach)] * len(ends)
        if not body:
            raise ValueError("no sphere or capsule geom of the MuJoCo model touches its floor")
        mass = float(model.body_mass.sum())
        weight = mass * float(np.linalg.norm(model.opt.gravity))
        names = [_group_name(model, b) for b in body]
        groups = tuple(dict.fromkeys(names))  # in order of first appearance
        return cls(tuple(body), tuple(offset), tuple(radius), float(model.geom_pos[floor, 2]),
                   weight, tuple(groups.index(n) for n in names), groups)  # fmt: skip


def _group_name(model: mujoco.MjModel, body: int) -> str:
    """A leaf body's own name; `LIMBS` for a body whose children are all leaves; `TRUNK`."""
    parents = model.body_parentid
    children = [b for b in range(1, model.nbody) if parents[b] == body]
    if not children:
        return model.body(body).name or f"body{body}"
    if all(not any(parents[c] == k for c in range(1, model.nbody)) for k in children):
        return LIMBS
    return TRUNK


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


@dataclass(frozen=True)
class ContactLaw:
    """Starting constants of the law: stiffness k (body weights per point at 1 cm to the
    exponent e), damping c (s/m) and friction mu."""

    stiffness: float
    exponent: float
    damping: float
    friction: float

    @classmethod
    def from_physics(cls, hold_depth: float = HOLD_DEPTH, exponent: float = START_EXPONENT,
                     friction: float = 1.0) -> ContactLaw:  # fmt: skip
        """Two points hold the body's weight W at `hold_depth` (W k (d / delta)^e = W / 2);
        the stance's vertical oscillation (omega^2 = e g / d) is critically damped by the
        Hunt-Crossley term (c = 2 omega / g)."""
        stiffness = 0.5 * (PENETRATION_UNIT / hold_depth) ** exponent
        damping = 2.0 * math.sqrt(exponent / (GRAVITY * hold_depth))
        return cls(stiffness, exponent, damping, friction)


@dataclass
class ImplicitTerms:
    """What the linearly implicit step needs at (q, qd), per point: the spring force s
    (..., P), the normal and tangential damping gains (..., P) of f = f(v+), the points'
    velocities (..., P, 3) and their Jacobians by columns: `jacobian` (..., P, 3, D) holds
    point p's columns for the DoFs `columns[p]` (D,) of the `nv` (zero columns where fewer
    DoFs move it). `chains`: points [start, stop) share their first `width` columns (the
    DoFs of one chain of bodies from the root), and `pairs` places each chain's
    (width, width) block in the flattened (nv, nv), so J^T K J skips the other chains' DoFs."""

    spring: Tensor
    normal_gain: Tensor
    tangential_gain: Tensor
    jacobian: Tensor
    velocity: Tensor
    columns: Tensor
    nv: int
    chains: tuple[tuple[int, int, int], ...]
    pairs: Tensor

    def generalized(self, active: Tensor, dt: float) -> tuple[Tensor, Tensor]:
        """For the points `active` (..., P): the contact force at the step's start velocity,
        J^T (f0 - K J qd) (..., nv), and the added inertia dt J^T K J (..., nv, nv)."""
        on = active.to(self.spring.dtype)
        gain = torch.stack([self.tangential_gain, self.tangential_gain, self.normal_gain], -1)
        gain = gain * on.unsqueeze(-1)  # (..., P, 3)
        f0 = torch.zeros_like(self.velocity)
        f0 = torch.cat([f0[..., :2], (self.spring * on).unsqueeze(-1)], -1)
        point_force = f0 - gain * self.velocity  # (..., P, 3)
        local = torch.einsum("...pkd,...pk->...pd", self.jacobian, point_force)  # (..., P, D)
        force = _scatter(local, self.columns, self.nv)
        weighted = self.jacobian * gain.unsqueeze(-1)  # K J, (..., P, 3, D)
        blocks = [
            torch.einsum(
                "...pkd,...pke->...de",
                self.jacobian[..., start:stop, :, :width],
                weighted[..., start:stop, :, :width],
            ).flatten(-2)
            for start, stop, width in self.chains
        ]  # (..., width^2) each
        added = _scatter(dt * torch.cat(blocks, -1), self.pairs, self.nv * self.nv)
        return force, added.unflatten(-1, (self.nv, self.nv))

    def normal_velocity(self, qd: Tensor) -> Tensor:
        """Each point's normal velocity at generalized velocity qd (..., nv) -> (..., P)."""
        return (self.jacobian[..., 2, :] * _gather(qd, self.columns)).sum(-1)


@dataclass
class JointTerms(ImplicitTerms):
    """`ImplicitTerms` of points that are single DoFs (`dofs` (L,), pushed along `direction`
    (..., L)), as the joint limits are: the added inertia is diagonal."""

    dofs: Tensor
    direction: Tensor

    def generalized(self, active: Tensor, dt: float) -> tuple[Tensor, Tensor]:
        on = active.to(self.spring.dtype)
        gain = self.normal_gain * on  # (..., L)
        push = self.direction * (self.spring * on - gain * self.velocity[..., 2])
        zeros = self.spring.new_zeros((*self.spring.shape[:-1], self.nv))
        force = zeros.index_add(-1, self.dofs, push)
        added = torch.diag_embed(zeros.index_add(-1, self.dofs, dt * gain))
        return force, added


def _gather(x: Tensor, columns: Tensor) -> Tensor:
    """x's entries at `columns` (C...): (..., n) -> (..., C...)."""
    return x.index_select(-1, columns.reshape(-1)).unflatten(-1, columns.shape)


def _scatter(values: Tensor, index: Tensor, size: int) -> Tensor:
    """Sums `values` (..., I...) into `size` slots by `index` (I...): (..., size)."""
    flat = values.flatten(-index.dim())
    out = flat.new_zeros((*flat.shape[:-1], size))
    return out.index_add(-1, index.reshape(-1), flat)


class ContactModel(nn.Module):
    """Generalized contact forces of a body tree on a floor: (q, qd) -> tau (..., nv).

    Args:
        fk: the tree's forward kinematics (`ForwardKinematics.from_mujoco`).
        points: the contact points (`ContactPoints.from_mujoco`), with their groups.
        start: the law's starting constants, the same for every group.
        implicit: models step it with `implicit_acceleration` (else explicitly, as a force).
    """

    def __init__(
        self, fk: ForwardKinematics, points: ContactPoints, start: ContactLaw | None = None,
        implicit: bool = True,
    ) -> None:  # fmt: skip
        super().__init__()
        if len(points.body) != len(points.offset) or len(points.body) != len(points.radius):
            raise ValueError("contact points need a body, an offset and a radius each")
        points, layout = _by_chains(fk, points)  # each chain's points together
        self.fk, self.points, self.implicit, self.nv = fk, points, implicit, len(fk.dof_body)
        self.chains = layout.chains
        buffers = dict(  # from the MJCF: not saved with the weights
            offset=torch.tensor(points.offset, dtype=torch.float64),  # (P, 3)
            radius=torch.tensor(points.radius, dtype=torch.float64),  # (P,)
            body=torch.tensor(points.body, dtype=torch.long),
            group=torch.tensor(points.group, dtype=torch.long),
            columns=layout.columns,  # (P, D)
            in_chain=layout.in_chain,  # (P, D)
            pairs=layout.pairs,  # (sum of the chains' D^2,)
        )
        for name, value in buffers.items():
            self.register_buffer(name, value, persistent=False)
        self.register_load_state_dict_pre_hook(_drop_saved_points)
        self.register_buffer("rotational", torch.tensor(fk.rotational))  # (nv,)
        law = start or ContactLaw.from_physics()
        full = lambda v: torch.full((len(points.groups),), float(v))  # noqa: E731
        self.log_stiffness = nn.Parameter(full(math.log(law.stiffness)))
        self.raw_exponent = nn.Parameter(full(_inverse_softplus(law.exponent - 1.0)))
        self.raw_damping = nn.Parameter(full(_inverse_softplus(law.damping)))
        self.raw_friction = nn.Parameter(full(_inverse_softplus(law.friction)))

    @classmethod
    def from_mujoco(cls, model: mujoco.MjModel, start: ContactLaw | None = None,
                    implicit: bool = True) -> ContactModel:  # fmt: skip
        return cls(ForwardKinematics.from_mujoco(model), ContactPoints.from_mujoco(model), start,
                   implicit)  # fmt: skip

    def law(self) -> dict[str, Tensor]:
        """The learned constants per group (G,): stiffness k, exponent e, damping c (s/m),
        friction mu."""
        return dict(
            stiffness=self.log_stiffness.exp(),
            exponent=1.0 + F.softplus(self.raw_exponent),
            damping=F.softplus(self.raw_damping),
            friction=F.softplus(self.raw_friction),
        )

    def point_law(self, like: Tensor) -> dict[str, Tensor]:
        """The constants of each point (P,), on `like`'s device and dtype."""
        return {k: v.to(like).index_select(0, self.group) for k, v in self.law().items()}

    def forward(self, q: Tensor, qd: Tensor) -> Tensor:
        """The generalized contact force: (..., nq), (..., nv) -> (..., nv)."""
        position, jacobian = self.chain_kinematics(q)
        velocity = self._velocity(jacobian, qd)
        force = self.point_forces(position, velocity)
        local = torch.einsum("...pkd,...pk->...pd", jacobian, force)
        return _scatter(local, self.columns, self.nv)

    def contact_state(self, q: Tensor, qd: Tensor) -> ContactState:
        """The points, their velocities and the forces on them at (q, qd)."""
        position, jacobian = self.chain_kinematics(q)
        velocity = self._velocity(jacobian, qd)
        return ContactState(position, velocity, self.point_forces(position, velocity))

    def _velocity(self, jacobian: Tensor, qd: Tensor) -> Tensor:
        """The points' velocities J qd from their Jacobian columns (..., P, 3, D). (..., P, 3)"""
        return torch.einsum("...pkd,...pd->...pk", jacobian, _gather(qd, self.columns))

    def kinematics(self, q: Tensor, frames: Frames | None = None) -> tuple[Tensor, Tensor]:
        """The points (..., P, 3) and their Jacobians (..., P, 3, nv) at q (..., nq):
        dp_i/dt = J_i qd. `frames`: the tree's `ForwardKinematics.dof_axes(q)` where the
        caller has it already."""
        position, jacobian = self.chain_kinematics(q, frames)
        dense = jacobian.new_zeros((*jacobian.shape[:-1], self.nv))
        index = self.columns.unsqueeze(-2).expand(jacobian.shape[-3:])  # (P, 3, D)
        return position, dense.scatter_add(-1, index.expand_as(jacobian), jacobian)

    def chain_kinematics(self, q: Tensor, frames: Frames | None = None) -> tuple[Tensor, Tensor]:
        """`kinematics` by columns: the points (..., P, 3) and each one's Jacobian columns
        (..., P, 3, D) for its DoFs `columns` (P, D), zero past the DoFs that move it."""
        poses, axes = frames or self.fk.dof_axes(q)
        pos = poses.xpos.index_select(-2, self.body)
        mat = poses.xmat.index_select(-3, self.body)
        position = pos + (mat * self.offset.to(q).unsqueeze(-2)).sum(-1)  # (..., P, 3)
        anchor, axis = axes.anchor[..., self.columns, :], axes.axis[..., self.columns, :]
        lever = position.unsqueeze(-2) - anchor  # (..., P, D, 3)
        turn = torch.linalg.cross(axis, lever, dim=-1)
        rotational = self.rotational[self.columns].unsqueeze(-1)  # (P, D, 1)
        columns = torch.where(rotational, turn, axis) * self.in_chain.to(q).unsqueeze(-1)
        return position, columns.transpose(-1, -2)  # (..., P, 3, D)

    def _spring(self, position: Tensor, law: dict[str, Tensor]) -> tuple[Tensor, Tensor]:
        """Penetration d (at most `MAX_DEPTH`) and spring force s = W k (d / delta)^e (0 without
        contact). (..., P)"""
        depth = torch.clamp(
            self.points.floor + self.radius.to(position) - position[..., 2], 0, MAX_DEPTH
        )
        ratio = torch.clamp(depth / PENETRATION_UNIT, min=1e-12)  # log(0): no NaN gradient
        spring = torch.where(
            depth > 0, self.points.weight * law["stiffness"] * ratio.pow(law["exponent"]), 0.0
        )
        return depth, spring

    def point_forces(self, position: Tensor, velocity: Tensor) -> Tensor:
        """Forces (..., P, 3) on points at `position` moving at `velocity` (..., P, 3)."""
        law = self.point_law(position)
        _, spring = self._spring(position, law)
        normal = spring * torch.clamp(1.0 - law["damping"] * velocity[..., 2], min=0.0)
        slip = velocity[..., :2]  # (..., P, 2)
        speed = torch.sqrt(slip.square().sum(-1, keepdim=True) + SLIP_SPEED**2)
        tangential = -law["friction"].unsqueeze(-1) * normal.unsqueeze(-1) * slip / speed
        return torch.cat([tangential, normal.unsqueeze(-1)], dim=-1)

    def implicit_terms(
        self, q: Tensor, qd: Tensor, dt: float, frames: Frames | None = None
    ) -> ImplicitTerms:
        """The law linearised about the end of a step of `dt` (`frames`: as `kinematics`):
        the normal force
        s(d - dt v_n+) (1 - c v_n+) ~ s - (dt ds/dd + s c) v_n+, and friction as a damping
        of the slip, mu f_n / sqrt(|v_t|^2 + eps^2) with f_n at the step's start, times -v_t+
        (inside the cone while the slip does not grow)."""
        position, jacobian = self.chain_kinematics(q, frames)
        velocity = self._velocity(jacobian, qd)
        law = self.point_law(position)
        depth, spring = self._spring(position, law)
        stiffness = law["exponent"] * spring / torch.clamp(depth, min=1e-9)  # ds/dd
        normal_gain = dt * stiffness + spring * law["damping"]
        normal_now = spring * torch.clamp(1.0 - law["damping"] * velocity[..., 2], min=0.0)
        speed = torch.sqrt(velocity[..., :2].square().sum(-1) + SLIP_SPEED**2)
        tangential_gain = law["friction"] * normal_now / speed
        return ImplicitTerms(spring, normal_gain, tangential_gain, jacobian, velocity,
                             self.columns, self.nv, self.chains, self.pairs)  # fmt: skip

    def implicit_acceleration(
        self, q: Tensor, qd: Tensor, dt: float, mass_matrix: Tensor, force: Tensor
    ) -> Tensor:
        """`implicit_acceleration` with this model's contacts alone."""
        return implicit_acceleration([self.implicit_terms(q, qd, dt)], qd, dt, mass_matrix, force)


class JointLimits(nn.Module):
    """The limited hinges' and slides' ranges (known from the MJCF) as one-sided springs with
    Hunt-Crossley damping, stepped implicitly as the contacts are (`implicit_acceleration`):
    past a bound by d, the joint is pushed back by s (1 - c v), s = k d, v the speed into the
    bound. k holds the joint's largest actuator torque (`torque`) at `hold` past the bound;
    c = 2 / sqrt(hold g), as for the contacts' start. Fixed: nothing here is learned.

    Args:
        qpos: position index of each limited joint (L,).
        dofs: its velocity index (L,).
        lower: the lower end of its range (L,).
        upper: the upper end (L,).
        torque: the force its bound holds at `hold` (L,).
        hold: how far past a bound it holds `torque` (rad or m).
    """

    def __init__(
        self, qpos: Tensor, dofs: Tensor, lower: Tensor, upper: Tensor, torque: Tensor,
        hold: float = 0.01,
    ) -> None:  # fmt: skip
        super().__init__()
        self.register_buffer("qpos", qpos.to(torch.long))
        self.register_buffer("dofs", dofs.to(torch.long))
        self.register_buffer("lower", lower.to(torch.float64))
        self.register_buffer("upper", upper.to(torch.float64))
        self.register_buffer("stiffness", torque.to(torch.float64) / hold)
        self.damping = 2.0 / math.sqrt(hold * GRAVITY)

    @classmethod
    def from_mujoco(cls, model: mujoco.MjModel, fallback_torque: float = 1.0) -> JointLimits:
        """The limited hinges and slides of `model`; each holds its motor's largest torque
        (gear x control bound), `fallback_torque` without one."""
        scalar = (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE))
        joints = [j for j in range(model.njnt)
                  if model.jnt_limited[j] and int(model.jnt_type[j]) in scalar]  # fmt: skip
        torque = np.full(model.nv, fallback_torque)
        for a in range(model.nu):
            j = int(model.actuator_trnid[a, 0])
            if model.actuator_trntype[a] == mujoco.mjtTrn.mjTRN_JOINT and j >= 0:
                reach = abs(model.actuator_gear[a, 0]) * np.abs(model.actuator_ctrlrange[a]).max()
                dof = int(model.jnt_dofadr[j])
                torque[dof] = max(torque[dof], float(reach))
        dofs = [int(model.jnt_dofadr[j]) for j in joints]
        as_t = lambda x: torch.as_tensor(np.asarray(x))  # noqa: E731
        return cls(as_t([int(model.jnt_qposadr[j]) for j in joints]), as_t(dofs),
                   as_t(model.jnt_range[joints, 0]), as_t(model.jnt_range[joints, 1]),
                   as_t(torque[dofs]))  # fmt: skip

    def implicit_terms(self, q: Tensor, qd: Tensor, dt: float) -> JointTerms:
        """Each joint as a point whose "normal" is its coordinate out of its range (the bound
        it is nearer to), with no tangential part and one Jacobian column, its DoF. (..., L)"""
        pos = q.index_select(-1, self.qpos)
        lower, upper = self.lower.to(q), self.upper.to(q)
        below = pos - lower < upper - pos  # the lower bound is the nearer
        direction = torch.where(below, 1.0, -1.0).to(q)  # pushes back into the range
        depth = torch.clamp(torch.where(below, lower - pos, pos - upper), min=0)
        stiffness = self.stiffness.to(q)
        spring = stiffness * depth
        speed = direction * qd.index_select(-1, self.dofs)  # > 0: leaving the bound
        normal_gain = torch.where(depth > 0, dt * stiffness + spring * self.damping, 0.0)
        zeros = torch.zeros_like(direction)
        jacobian = torch.stack([zeros, zeros, direction], -1).unsqueeze(-1)  # (..., L, 3, 1)
        velocity = torch.stack([zeros, zeros, speed], -1)  # (..., L, 3)
        return JointTerms(spring, normal_gain, zeros, jacobian, velocity, self.dofs.unsqueeze(-1),
                          qd.shape[-1], (), self.dofs[:0], self.dofs, direction)  # fmt: skip


def implicit_acceleration(
    parts: list[ImplicitTerms], qd: Tensor, dt: float, mass_matrix: Tensor, force: Tensor
) -> Tensor:
    """qdd of a step of `dt` with every part (contacts, joint limits) taken implicitly:
    (M + dt sum J^T K J) qdd = force + sum J^T (f0 - K J qd), `force` every other generalized
    force (bias subtracted).

    Two passes: points whose normal force at the first pass's end velocity would pull
    (s - K_n v_n+ < 0: leaving faster than the spring can follow) are left out of the second.
    (..., nv), (..., nv, nv), (..., nv) -> (..., nv)"""
    active = [t.spring > 0 for t in parts]
    qdd = _solve(mass_matrix, force, parts, active, dt)
    end = qd + dt * qdd
    pushes = [t.spring - t.normal_gain * t.normal_velocity(end) > 0 for t in parts]
    return _solve(
        mass_matrix, force, parts, [a & p for a, p in zip(active, pushes, strict=True)], dt
    )


def _solve(
    mass_matrix: Tensor, force: Tensor, parts: list[ImplicitTerms], active: list[Tensor],
    dt: float,
) -> Tensor:  # fmt: skip
    total, added = force, mass_matrix
    for terms, on in zip(parts, active, strict=True):
        extra, inertia = terms.generalized(on, dt)
        total, added = total + extra, added + inertia
    # equilibrated (unit diagonal): stiff contacts add gains 10^6 times M's on a few DoFs
    scale = added.diagonal(dim1=-2, dim2=-1).rsqrt()  # (..., nv)
    factor = torch.linalg.cholesky_ex(added * scale.unsqueeze(-1) * scale.unsqueeze(-2)).L
    solved = torch.cholesky_solve((total * scale).unsqueeze(-1), factor).squeeze(-1)
    return solved * scale


def _drop_saved_points(
    module: nn.Module, state: dict[str, Tensor], prefix: str, *_: object
) -> None:
    """Weights saved before the points were grouped by chain hold them in the MJCF's order
    (and a dense mask of the DoFs that move them): the MJCF gives them again, so they go."""
    for name in ("offset", "radius", "body", "group", "moves"):
        state.pop(prefix + name, None)


def _dofs_above(fk: ForwardKinematics, body: int) -> list[int]:
    """The DoFs that move `body`: those of it and of its ancestors, in order."""
    above = _subtree_mask(fk.parent, body)
    return [v for v, b in enumerate(fk.dof_body) if above[b]]


@dataclass(frozen=True)
class ChainLayout:
    """Contact points grouped by the chain of DoFs that moves them (`ImplicitTerms`)."""

    chains: tuple[tuple[int, int, int], ...]  # per chain: its points [start, stop), its width
    columns: Tensor  # (P, D) each point's chain's DoFs, padded with DoF 0
    in_chain: Tensor  # (P, D) 1 where the column's DoF moves the point
    pairs: Tensor  # (sum of the chains' width^2,) each chain's block in the flattened (nv, nv)


def _by_chains(fk: ForwardKinematics, points: ContactPoints) -> tuple[ContactPoints, ChainLayout]:
    """The points reordered by chain, and their layout. A chain is the DoFs that move a point
    and no other point's DoFs contain (a leaf of the tree that holds points); every point
    joins the first chain whose DoFs hold its own."""
    moving = [_dofs_above(fk, b) for b in points.body]
    chains = sorted(dict.fromkeys(tuple(dofs) for dofs in moving), key=len, reverse=True)
    tops: list[tuple[int, ...]] = []
    for chain in chains:
        if not any(set(chain) <= set(top) for top in tops):
            tops.append(chain)
    member = [next(i for i, top in enumerate(tops) if set(dofs) <= set(top)) for dofs in moving]
    order = sorted(range(len(moving)), key=lambda p: member[p])
    width, nv = max(len(top) for top in tops), len(fk.dof_body)
    pad = lambda row, value: list(row) + [value] * (width - len(row))  # noqa: E731
    columns = [pad(tops[member[p]], 0) for p in order]
    in_chain = [pad([float(v in moving[p]) for v in tops[member[p]]], 0.0) for p in order]
    bounds = [sum(member.count(j) for j in range(i)) for i in range(len(tops) + 1)]
    layout = ChainLayout(
        chains=tuple((bounds[i], bounds[i + 1], len(top)) for i, top in enumerate(tops)),
        columns=torch.tensor(columns, dtype=torch.long),
        in_chain=torch.tensor(in_chain, dtype=torch.float64),
        pairs=torch.tensor([a * nv + b for top in tops for a in top for b in top]),
    )
    pick = lambda values: tuple(values[p] for p in order)  # noqa: E731
    points = replace(points, body=pick(points.body), offset=pick(points.offset),
                     radius=pick(points.radius), group=pick(points.group))  # fmt: skip
    return points, layout


def _subtree_mask(parent: list[int], body: int) -> list[bool]:
    """Per body b: is `body` b itself or below it in the tree (b an ancestor of `body`)."""
    ancestors = set()
    while body > 0:
        ancestors.add(body)
        body = parent[body]
    return [b in ancestors for b in range(len(parent))]


def floor_parts(
    model: mujoco.MjModel, weight: float, contacts: bool, implicit: bool, joint_limits: bool
) -> tuple[ContactModel | None, JointLimits | None]:
    """The contact model (its weight unit `weight`, solved implicitly or not) where `contacts`
    and the MJCF has a floor its geoms can touch (else none, logged), and the joint limits
    where `joint_limits`."""
    contact = None
    if contacts:
        try:
            points = ContactPoints.from_mujoco(model)
        except ValueError as err:
            log.info("contacts: none in this MJCF (%s)", err)
        else:
            contact = ContactModel(ForwardKinematics.from_mujoco(model),
                                   replace(points, weight=weight), implicit=implicit)  # fmt: skip
    limits = JointLimits.from_mujoco(model) if joint_limits else None
    return contact, limits
