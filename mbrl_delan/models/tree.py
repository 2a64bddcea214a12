"""A known kinematic tree with learned inertias: `RigidBodyTree`, and the equations of motion
over it, alone or with a DeLaN residual Lagrangian beside it (`TreeDynamics`).

A user almost always knows the kinematic tree of their robot (the MJCF or URDF: joint axes,
body frames, gears, collision geometry); what they do not know well is what each body weighs
and how that mass is spread, and each joint's damping and rotor inertia. The tree keeps the
geometry and learns those numbers by gradient, physically consistent for any value:

- each moving body's inertial parameters as the pseudo-inertia J = [[Sigma, h], [h^T, m]]
  (Sigma = integral of r r^T dm about the body's origin, h = m c, m the mass), J = U U^T with
  U = U_0 V, U_0 the start's upper factor and V upper triangular with a positive (exponential)
  diagonal: J is positive definite for every raw value, which is exactly positive mass, a
  positive definite inertia about the centre of mass and its triangle inequalities;
- each hinge's and slide's viscous damping and armature, exp(raw) (positive);
- the joints' springs (MuJoCo's ``stiffness`` about ``springref``) are the MJCF's, fixed; or,
  with ``learn_springs``, each hinge's and slide's stiffness exp(raw) (positive, started at
  the MJCF's, a zero one at `SPRING_FLOOR` of the largest) and rest position learned too: a
  robot whose passive springs the file does not hold (an exoskeleton, a cable) keeps one
  spring per joint.

The dynamics, in MuJoCo's coordinates (a free root's linear velocity in the world frame and
its angular velocity in the body frame), from spatial vectors in world axes about the first
moving body's origin (Plücker coordinates; `spatial_cross`), on one forward kinematics per
configuration (`ForwardKinematics.dof_axes`, shared with the contact model):

- S_v (..., nv, 6): each DoF's motion per unit velocity (axis, lever x axis); I_b each
  moving body's spatial inertia in world axes (`world_inertia`);
- M by composite rigid bodies: M_ij = S_i^T Ic_j S_j for DoF i at or above DoF j, Ic_j the
  summed inertia of DoF j's body and all below it, plus diag(armature);
- c + g by Newton-Euler in world axes: each body's twist V_b = sum of S_v qd_v above it, its
  bias acceleration A_b = sum of (V_frame(v) x S_v) qd_v (the frame each axis is fixed in,
  `_frames`) plus gravity as an upward acceleration of the base; the body forces
  I_b A_b + V_b x* I_b V_b summed below each DoF and projected on S_v. For a free root the
  gravity term is |g| times M's column of the vertical translation, at any parameters;
- passive: k (q - q_spring) + b qd.

`tests/test_tree.py` checks M against `mj_fullM` and c + g against `qfrc_bias` at the MJCF's
own parameters, on Humanoid-v5 and an arm.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np
import torch
from torch import Tensor, nn

from mbrl_delan.models.contact import _subtree_mask
from mbrl_delan.models.inertial import inertial_parameters, moving_bodies, pseudo_inertia
from mbrl_delan.models.kernels import cholesky_solve
from mbrl_delan.models.lagrangian import LagrangianDynamics, LagrangianTerms
from mbrl_delan.systems.forward_kinematics import (
    BALL,
    FREE,
    HINGE,
    SLIDE,
    ForwardKinematics,
    Frames,
)
from mbrl_delan.systems.system import System

_UPPER = torch.triu_indices(4, 4, 1)  # V's entries above the diagonal, row by row
FLOOR = 1e-12  # a start's zero damping or armature starts at this share of the largest (log scale)
SPRING_FLOOR = 1e-2  # a zero spring learned starts at this share of the largest (log scale)


def spatial_cross(a: Tensor, b: Tensor) -> Tensor:
    """Motion cross product a x b of spatial motion vectors (w, v): (w x b_w, w x b_v + v x
    b_w). (..., 6), (..., 6) -> (..., 6)"""
    w, v = a[..., :3], a[..., 3:]
    return torch.cat(
        [torch.linalg.cross(w, b[..., :3], dim=-1),
         torch.linalg.cross(w, b[..., 3:], dim=-1) + torch.linalg.cross(v, b[..., :3], dim=-1)],
        dim=-1,
    )  # fmt: skip


def spatial_cross_force(a: Tensor, f: Tensor) -> Tensor:
    """Force cross product a x* f of a motion vector (w, v) and a force (n, f): (w x n + v x f,
    w x f). (..., 6), (..., 6) -> (..., 6)"""
    w, v = a[..., :3], a[..., 3:]
    return torch.cat(
        [torch.linalg.cross(w, f[..., :3], dim=-1) + torch.linalg.cross(v, f[..., 3:], dim=-1),
         torch.linalg.cross(w, f[..., 3:], dim=-1)],
        dim=-1,
    )  # fmt: skip


@dataclass(frozen=True)
class TreeStart:
    """Where a tree's learned numbers start: per moving body its pi = [m, h (3), I about the
    body origin (xx, yy, zz, xy, xz, yz)] in the body frame, per DoF damping and armature."""

    inertial: np.ndarray  # (B, 10)
    damping: np.ndarray  # (nv,)
    armature: np.ndarray  # (nv,)

    @classmethod
    def of_model(cls, model: mujoco.MjModel) -> TreeStart:
        """The MuJoCo model's own numbers (the truth when it is the env's MJCF)."""
        bodies = moving_bodies(model)
        inertial = np.stack([inertial_parameters(model, b) for b in bodies])
        return cls(inertial, model.dof_damping.copy(), model.dof_armature.copy())


DENSITY = 1000.0  # kg/m^3: the geometric start's one density (water; a human body is ~1,010)
WRONG_MASS_SPREAD = 0.5  # the documented start: each body's mass and inertia x U(0.5, 1.5) ...
WRONG_SEED = 0  # ... drawn with this seed, as the white box's documented start
WRONG_JOINTS = {"damping": 2.0, "armature": 0.5}  # ... and the joints' numbers x these
MIN_MASS_SHARE = 1e-3  # a moving body without geoms weighs this share of the total


def geometric_start(spec: mujoco.MjSpec, total_mass: float | None = None,
                    density: float = DENSITY) -> TreeStart:  # fmt: skip
    """What a user knows without weighing parts: each moving body's mass and inertia from
    its geoms' volumes at one `density` (MuJoCo's inertia from geometry, every geom at that
    density, the MJCF's own inertial numbers ignored), scaled so the bodies weigh
    `total_mass` when it is given; the joints' damping and armature as the MJCF gives them.
    A moving body that weighs nothing by its geoms gets `MIN_MASS_SHARE` of the total as a
    small sphere."""
    spec = spec.copy()
    spec.compiler.inertiafromgeom = mujoco.mjtInertiaFromGeom.mjINERTIAFROMGEOM_TRUE
    for geom in spec.geoms:
        geom.mass, geom.density = float("nan"), density  # nan: from the density
    model = spec.compile()
    start = TreeStart.of_model(model)
    inertial = start.inertial.copy()
    light = inertial[:, 0] <= 0
    if light.any():
        mass = MIN_MASS_SHARE * float(inertial[:, 0].sum())
        radius = 0.05  # m
        inertial[light] = [mass, 0, 0, 0, *(3 * [0.4 * mass * radius**2]), 0, 0, 0]
    if total_mass is not None:
        inertial *= total_mass / float(inertial[:, 0].sum())
    return TreeStart(inertial, start.damping, start.armature)


def documented_start(spec: mujoco.MjSpec, total_mass: float | None = None) -> TreeStart:
    """The geometric start made wrong in a documented way: each body's mass and inertia x
    U(1 - `WRONG_MASS_SPREAD`, 1 + it) drawn with `WRONG_SEED` (its centre of mass kept),
    damping and armature x `WRONG_JOINTS`. Where the MJCF's inertias come from its geometry
    at one density (Humanoid-v5), the plain geometric start is the truth; this one is not."""
    start = geometric_start(spec, total_mass)
    rng = np.random.default_rng(WRONG_SEED)
    scale = rng.uniform(1 - WRONG_MASS_SPREAD, 1 + WRONG_MASS_SPREAD, len(start.inertial))
    return TreeStart(start.inertial * scale[:, None],
                     start.damping * WRONG_JOINTS["damping"],
                     start.armature * WRONG_JOINTS["armature"])  # fmt: skip


def armature_start(model: mujoco.MjModel, share: float) -> np.ndarray:
    """Each DoF's armature as the MJCF gives it, or where it gives none `share` x the DoF's
    diagonal of M(qpos0): a start the fit can move (a zero start sits at the log floor, where
    its gradient vanishes, and a residual has to carry the armature). (nv,)"""
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    mass = np.zeros((model.nv, model.nv))
    mujoco.mj_fullM(model, data, mass)
    armature = model.dof_armature.copy()
    return np.where(armature > 0, armature, share * np.diag(mass))


def upper_factor(J: np.ndarray) -> np.ndarray:
    """U upper triangular with a positive diagonal and U U^T = J (positive definite). (4, 4)"""
    flip = np.arange(3, -1, -1)
    return np.linalg.cholesky(J[np.ix_(flip, flip)])[np.ix_(flip, flip)]


@dataclass
class BodyInertia:
    """Rigid bodies' inertia about the reference point in world axes: mass m (..., B), first
    moment h (..., B, 3) and rotational inertia I (..., B, 3, 3); as a spatial inertia
    [[I, [h]x], [[h]x^T, m 1]], applied to motions by `apply`."""

    mass: Tensor
    first_moment: Tensor
    rotational: Tensor

    def apply(self, motion: Tensor) -> Tensor:
        """The spatial inertia times motions (w, v) (..., 6): (I w + h x v, m v - h x w)."""
        w, v, h = motion[..., :3], motion[..., 3:], self.first_moment
        angular = (self.rotational * w.unsqueeze(-2)).sum(-1) + torch.linalg.cross(h, v, dim=-1)
        linear = self.mass.unsqueeze(-1) * v - torch.linalg.cross(h, w, dim=-1)
        return torch.cat([angular, linear], dim=-1)

    def summed(self, groups: Tensor) -> BodyInertia:
        """sum_c groups[b, c] (body c's inertia) for each row b of `groups` (G, B)."""
        flat = torch.cat([self.mass.unsqueeze(-1), self.first_moment,
                          self.rotational.flatten(-2)], dim=-1)  # (..., B, 13)  # fmt: skip
        total = (groups.to(flat).unsqueeze(-1) * flat.unsqueeze(-3)).sum(-2)  # (..., G, 13)
        return BodyInertia(total[..., 0], total[..., 1:4], total[..., 4:].unflatten(-1, (3, 3)))

    def select(self, index: Tensor) -> BodyInertia:
        """The inertias of bodies `index` (K,)."""
        return BodyInertia(self.mass.index_select(-1, index),
                           self.first_moment.index_select(-2, index),
                           self.rotational.index_select(-3, index))  # fmt: skip


@dataclass
class Kinematics:
    """What the dynamics need of a configuration q, about the reference point (the first
    moving body's origin) in world axes: each DoF's motion per unit velocity and each moving
    body's inertia."""

    motion: Tensor  # S (..., nv, 6)
    inertia: BodyInertia  # (..., B)


class RigidBodyTree(nn.Module):
    """The rigid-body dynamics of a known kinematic tree with learned inertial parameters,
    damping and armature (module docstring).

    Args:
        fk: the tree's forward kinematics (`ForwardKinematics.from_mujoco`).
        bodies: the moving bodies (`moving_bodies`), in tree order.
        start: the learned numbers' start (`TreeStart`).
        gravity: the world's gravity (3,), MuJoCo's ``opt.gravity``.
        stiffness, spring_ref: each DoF's spring (nv,) and its rest position (nv,; the
            coordinate's value, hinges and slides only).
        spring_q: the q index of each DoF's coordinate (nv,; -1 where it has none).
        scalar: which DoFs are hinges or slides (damping and armature are learned there only).
        learn_springs: learn each scalar DoF's stiffness and rest position from these starts.
    """

    def __init__(
        self, fk: ForwardKinematics, bodies: list[int], start: TreeStart, gravity: np.ndarray,
        stiffness: np.ndarray, spring_ref: np.ndarray, spring_q: np.ndarray, scalar: np.ndarray,
        learn_springs: bool = False,
    ) -> None:  # fmt: skip
        super().__init__()
        self.fk, self.bodies = fk, bodies
        nv, B = len(fk.dof_body), len(bodies)
        f64 = torch.float64
        factors = np.stack([upper_factor(pseudo_inertia(pi)) for pi in start.inertial])
        self.register_buffer("start_factor", torch.tensor(factors, dtype=f64))  # U_0 (B, 4, 4)
        self.raw_inertia = nn.Parameter(torch.zeros(B, 10, dtype=f64))  # V: log diag, upper
        scalar_t = torch.tensor(scalar, dtype=torch.bool)
        self.register_buffer("scalar", scalar_t)
        self.raw_damping = nn.Parameter(self._log_start(start.damping, scalar))
        self.raw_armature = nn.Parameter(self._log_start(start.armature, scalar))
        self.register_buffer("gravity_accel", torch.tensor(
            [0.0, 0.0, 0.0, *(-np.asarray(gravity, dtype=float))], dtype=f64))  # fmt: skip
        self.learn_springs = learn_springs
        if learn_springs:
            self.raw_stiffness = nn.Parameter(self._log_start(stiffness, scalar, SPRING_FLOOR))
            self.spring_ref = nn.Parameter(torch.tensor(spring_ref, dtype=f64))
        else:
            self.register_buffer("stiffness", torch.tensor(stiffness, dtype=f64))
            self.register_buffer("spring_ref", torch.tensor(spring_ref, dtype=f64))
        self.register_buffer("spring_q", torch.tensor(np.maximum(spring_q, 0), dtype=torch.long))
        above = [_subtree_mask(fk.parent, b) for b in bodies]  # body b under body c: above[b][c]
        ancestry = [[above[i][fk.dof_body[v]] for v in range(nv)] for i in range(B)]
        self.register_buffer("ancestry", torch.tensor(ancestry, dtype=f64))  # (B, nv)
        self.register_buffer("frame", torch.tensor(_frames(fk), dtype=f64))  # (nv, nv)
        self.register_buffer("body_index", torch.tensor(bodies, dtype=torch.long))
        self.register_buffer("rotational", torch.tensor(fk.rotational))
        # subtree[b, c]: body c at or below body b; path[i, j]: DoF i at or above DoF j
        subtree = [[above[c][self.bodies[b]] for c in range(B)] for b in range(B)]
        self.register_buffer("subtree", torch.tensor(subtree, dtype=f64))  # (B, B)
        index = {body: i for i, body in enumerate(bodies)}
        dof_body = [index[b] for b in fk.dof_body]
        self.register_buffer("dof_subtree", torch.tensor([subtree[b] for b in dof_body],
                                                         dtype=f64))  # (nv, B)  # fmt: skip
        self.register_buffer("path", torch.tensor(_paths(fk), dtype=f64))  # (nv, nv)
        self.nv = nv

    @staticmethod
    def _log_start(values: np.ndarray, scalar: np.ndarray, share: float = FLOOR) -> Tensor:
        """log of a start (nv,), floored at `share` of the largest; 0 on DoFs not learned."""
        values = np.asarray(values, dtype=float)
        floor = share * max(float(values.max(initial=0.0)), 1.0)
        return torch.tensor(np.where(scalar, np.log(np.maximum(values, floor)), 0.0))

    @classmethod
    def from_mujoco(
        cls, model: mujoco.MjModel, start: TreeStart | None = None, learn_springs: bool = False
    ) -> RigidBodyTree:
        """The tree of a compiled MuJoCo model; `start` None: the model's own numbers; its
        springs started at the model's where `learn_springs`."""
        kinds = [int(model.jnt_type[model.dof_jntid[v]]) for v in range(model.nv)]
        scalar = np.array([k in (HINGE, SLIDE) for k in kinds])
        spring_q = np.array(
            [model.jnt_qposadr[model.dof_jntid[v]] if scalar[v] else -1 for v in range(model.nv)]
        )
        spring_ref = np.array(
            [model.qpos_spring[spring_q[v]] if scalar[v] else 0.0 for v in range(model.nv)]
        )
        stiffness = np.array([model.jnt_stiffness[model.dof_jntid[v]] if scalar[v] else 0.0
                              for v in range(model.nv)])  # fmt: skip
        return cls(ForwardKinematics.from_mujoco(model), moving_bodies(model),
                   start or TreeStart.of_model(model), model.opt.gravity.copy(), stiffness,
                   spring_ref, spring_q, scalar, learn_springs)  # fmt: skip

    # ------------------------------------------------------------------ the learned numbers

    def pseudo_inertia(self) -> Tensor:
        """J = U U^T of every moving body, in its frame. (B, 4, 4)"""
        B = self.raw_inertia.shape[0]
        raw = self.raw_inertia
        V = torch.diag_embed(raw[:, :4].exp())
        V = V.index_put((torch.arange(B).repeat_interleave(6),
                         _UPPER[0].repeat(B), _UPPER[1].repeat(B)),
                        raw[:, 4:].reshape(-1), accumulate=True)  # fmt: skip
        U = self.start_factor @ V
        return U @ U.transpose(-1, -2)

    def inertial(self) -> dict[str, Tensor]:
        """Every moving body's mass (B,), first moment h = m c (B, 3) and rotational inertia
        about its origin (B, 3, 3), in its frame."""
        J = self.pseudo_inertia()
        sigma = J[:, :3, :3]
        trace = sigma.diagonal(dim1=-2, dim2=-1).sum(-1)
        eye = torch.eye(3, dtype=J.dtype, device=J.device)
        return {"mass": J[:, 3, 3], "first_moment": J[:, :3, 3],
                "inertia": trace[:, None, None] * eye - sigma}  # fmt: skip

    @property
    def damping(self) -> Tensor:
        """Viscous damping per DoF (nv,); 0 on a free or ball joint."""
        return torch.where(self.scalar, self.raw_damping.exp(), 0.0)

    @property
    def armature(self) -> Tensor:
        """Armature per DoF (nv,); 0 on a free or ball joint."""
        return torch.where(self.scalar, self.raw_armature.exp(), 0.0)

    def total_mass(self) -> Tensor:
        return self.inertial()["mass"].sum()

    # ------------------------------------------------------------------ the dynamics

    def kinematics(self, q: Tensor, frames: Frames | None = None) -> Kinematics:
        """Each DoF's motion and each moving body's spatial inertia at q (..., nq), in q's
        dtype; `frames`: the tree's `ForwardKinematics.dof_axes(q)` where the caller has it."""
        poses, axes = frames or self.fk.dof_axes(q)
        xpos = poses.xpos.index_select(-2, self.body_index)  # (..., B, 3)
        rotation = poses.xmat.index_select(-3, self.body_index)
        reference = xpos[..., :1, :]
        rotational = self.rotational.unsqueeze(-1)
        lever = axes.anchor - reference  # (..., nv, 3)
        angular = torch.where(rotational, axes.axis, 0.0)
        linear = torch.where(rotational, torch.linalg.cross(lever, axes.axis, dim=-1), axes.axis)
        motion = torch.cat([angular, linear], dim=-1)  # (..., nv, 6)
        parts = {k: v.to(q) for k, v in self.inertial().items()}
        return Kinematics(motion, world_inertia(parts, xpos - reference, rotation))

    def mass_matrix(self, q: Tensor, kin: Kinematics | None = None) -> Tensor:
        """M(q) with the armature (MuJoCo's ``qM``), by composite rigid bodies:
        M_ij = S_i^T Ic_b(j) S_j for DoF i on the path from the root to DoF j. (..., nv, nv)"""
        kin = kin or self.kinematics(q)
        composite = kin.inertia.summed(self.dof_subtree)  # Ic of each DoF's body (..., nv)
        moved = composite.apply(kin.motion)  # Ic S_j (..., nv, 6)
        products = (kin.motion.unsqueeze(-2) * moved.unsqueeze(-3)).sum(-1)  # S_i . Ic S_j
        upper = products * self.path.to(q)
        diagonal = products.diagonal(dim1=-2, dim2=-1) + self.armature.to(q)
        return (
            upper
            + upper.transpose(-1, -2)
            + torch.diag_embed(diagonal - 2 * upper.diagonal(dim1=-2, dim2=-1))
        )

    def gravity(self, q: Tensor, kin: Kinematics | None = None) -> Tensor:
        """g(q): the generalized force that holds the tree against gravity. (..., nv)"""
        kin = kin or self.kinematics(q)
        accel = self.gravity_accel.to(q).expand(*kin.inertia.mass.shape, 6)
        return self._generalized(kin, kin.inertia.apply(accel))

    def bias(self, qd: Tensor, kin: Kinematics, gravity: bool = True) -> Tensor:
        """c(q, qd) (+ g(q) with `gravity`): MuJoCo's ``qfrc_bias``, in its
        (quasi-)velocities, by Newton-Euler. (..., nv)"""
        rates = kin.motion * qd.unsqueeze(-1)  # S_v qd_v (..., nv, 6)
        frame_velocity = _combine(self.frame.to(qd), rates)
        bias_rates = spatial_cross(frame_velocity, rates)  # dS_v/dt qd_v
        ancestry = self.ancestry.to(qd)
        twist = _combine(ancestry, rates)  # V_b (..., B, 6)
        accel = _combine(ancestry, bias_rates)  # A_b
        if gravity:
            accel = accel + self.gravity_accel.to(qd)
        inertia = kin.inertia
        force = inertia.apply(accel) + spatial_cross_force(twist, inertia.apply(twist))
        return self._generalized(kin, force)

    def _generalized(self, kin: Kinematics, force: Tensor) -> Tensor:
        """S_v . (the forces on the bodies at and below DoF v's body): body forces (..., B, 6)
        about the reference point as generalized forces. (..., nv)"""
        return (kin.motion * _combine(self.dof_subtree.to(force), force)).sum(-1)

    def coriolis(self, qd: Tensor, kin: Kinematics) -> Tensor:
        """c(q, qd): Coriolis and centrifugal forces. (..., nv)"""
        return self.bias(qd, kin, gravity=False)

    def passive(self, q: Tensor, qd: Tensor) -> Tensor:
        """Spring and damper force k (q - q_spring) + b qd (on the left: they resist). (..., nv)"""
        return self.spring(q) + self.damping.to(qd) * qd

    def spring_stiffness(self) -> Tensor:
        """Each DoF's spring stiffness k, learned or the MJCF's (0 off hinges and slides). (nv,)"""
        if not self.learn_springs:
            return self.stiffness
        return torch.where(self.scalar, self.raw_stiffness.exp(), 0.0)

    def spring(self, q: Tensor) -> Tensor:
        """The joints' springs k (q - q_spring). (..., nv)"""
        offset = q.index_select(-1, self.spring_q) - self.spring_ref.to(q)
        return self.spring_stiffness().to(q) * offset

    def potential_energy(self, q: Tensor) -> Tensor:
        """Gravity's and the springs' energy. (...)"""
        poses = self.fk(q)
        xpos = poses.xpos.index_select(-2, self.body_index)
        xmat = poses.xmat.index_select(-3, self.body_index)
        parts = {k: v.to(q) for k, v in self.inertial().items()}
        turned = (xmat * parts["first_moment"].unsqueeze(-2)).sum(-1)  # R h
        first = parts["mass"].unsqueeze(-1) * xpos + turned
        height = (first * self.gravity_accel[3:].to(q)).sum((-1, -2))
        offset = q.index_select(-1, self.spring_q) - self.spring_ref.to(q)
        return height + 0.5 * (self.spring_stiffness().to(q) * offset.square()).sum(-1)


def world_inertia(parts: dict[str, Tensor], position: Tensor, rotation: Tensor) -> BodyInertia:
    """The inertia about the reference point in world axes of bodies whose origins are at
    `position` (..., B, 3) from it, turned by `rotation` (..., B, 3, 3), from their mass (B,),
    first moment h (B, 3) and inertia about their origin (B, 3, 3) in their own axes:
    h_O = m r + R h and I_O = R I R^T + m (|r|^2 1 - r r^T) + 2 (r . R h) 1 - r (R h)^T -
    (R h) r^T."""
    mass, r = parts["mass"], position
    h = (rotation * parts["first_moment"].unsqueeze(-2)).sum(-1)  # R h (..., B, 3)
    half = (rotation.unsqueeze(-2) * parts["inertia"].unsqueeze(-3)).sum(-1)  # R I
    turned = (half.unsqueeze(-2) * rotation.unsqueeze(-3)).sum(-1)  # R I R^T
    eye = torch.eye(3, dtype=r.dtype, device=r.device)
    m = mass[:, None, None]
    cross = r.unsqueeze(-1) * h.unsqueeze(-2)
    square = (r * r).sum(-1)[..., None, None] * m + 2 * (r * h).sum(-1)[..., None, None]
    about = turned + square * eye - m * r.unsqueeze(-1) * r.unsqueeze(-2) - cross
    return BodyInertia(mass.expand(r.shape[:-1]), mass.unsqueeze(-1) * r + h,
                       about - cross.transpose(-1, -2))  # fmt: skip


def _combine(weights: Tensor, rows: Tensor) -> Tensor:
    """sum_k weights[i, k] rows[..., k, :] for a constant 0/1 matrix (I, K) and rows
    (..., K, d), as a broadcast product (fuses when compiled). -> (..., I, d)"""
    return (weights.unsqueeze(-1) * rows.unsqueeze(-3)).sum(-2)


def _frames(fk: ForwardKinematics) -> np.ndarray:
    """F (nv, nv): F[v, u] = 1 where DoF u moves the frame DoF v's axis is fixed in, so that
    dS_v/dt = (sum_u F[v, u] S_u qd_u) x S_v. A hinge's or slide's axis is fixed in its
    body's frame before its own joint (the DoFs above the body and the body's earlier ones;
    its own adds nothing, S x S = 0); a ball's or free joint's rotation axes are the body's own
    axes after the joint (its three DoFs too; for a free joint all six); a free joint's
    translations are along the world's axes (a zero row)."""
    joint = [(b, k, j.kind) for b, js in enumerate(fk.joints) for k, j in enumerate(js)
             for _ in range(NDOF[j.kind])]  # fmt: skip
    nv = len(joint)
    frames = np.zeros((nv, nv))
    for v, (body, k, kind) in enumerate(joint):
        if kind == FREE and not fk.rotational[v]:
            continue
        above = _subtree_mask(fk.parent, body)  # above[c]: body c is `body` or above it
        for u, (other, k_u, _) in enumerate(joint):
            same_body = other == body
            frames[v, u] = float(u <= v or k_u == k) if same_body else float(above[other])
    return frames


def _paths(fk: ForwardKinematics) -> np.ndarray:
    """P (nv, nv): P[i, j] = 1 where DoF i is DoF j or above it (on its body's path to the
    root, or earlier on the same body)."""
    nv = len(fk.dof_body)
    paths = np.zeros((nv, nv))
    for j in range(nv):
        above = _subtree_mask(fk.parent, fk.dof_body[j])
        for i in range(nv):
            same = fk.dof_body[i] == fk.dof_body[j]
            paths[i, j] = float(i <= j) if same else float(above[fk.dof_body[i]])
    return paths


NDOF = {FREE: 6, BALL: 3, SLIDE: 1, HINGE: 1}


class TreeDynamics(nn.Module):
    """The equations of motion of a `RigidBodyTree`, with a DeLaN residual Lagrangian beside
    it when `residual` is given: M = M_tree + M_res, c + g + d = the tree's (with its springs
    and damping) + the residual's (its Coriolis, potential and dissipation).

    The same interface as `LagrangianDynamics`, so `DeLaN` steps, fits and plans with it:
    `terms`, `mass_and_bias`, `inverse_dynamics`, `forward_dynamics`, `generalized_force`.
    `field` and `dissipation` are the residual's (None without), which the DeLaN's units from
    data set.
    """

    def __init__(
        self, tree: RigidBodyTree, actuation: Tensor, residual: LagrangianDynamics | None = None
    ) -> None:
        super().__init__()
        self.tree, self.residual = tree, residual
        self.register_buffer("actuation", actuation.clone())
        self.field = None if residual is None else residual.field
        self.dissipation = None if residual is None else residual.dissipation

    def generalized_force(self, action: Tensor) -> Tensor:
        """tau = B a: (..., nu) -> (..., n)."""
        return action @ self.actuation.to(action).transpose(-1, -2)

    def _tree_terms(
        self, q: Tensor, qd: Tensor, frames: Frames | None = None
    ) -> tuple[Tensor, Tensor]:
        """The tree's M (..., n, n) and c + g + springs + damping (..., n)."""
        kin = self.tree.kinematics(q, frames)
        return self.tree.mass_matrix(q, kin), self.tree.bias(qd, kin) + self.tree.passive(q, qd)

    def mass_and_bias(
        self, q: Tensor, qd: Tensor, damping_dt: float = 0.0, frames: Frames | None = None
    ) -> tuple[Tensor, Tensor]:
        """M (..., n, n) and c + g + d (..., n); `damping_dt` > 0: the damping (the tree's
        and the residual's friction slope) taken at the end of a step that long (M + dt
        dd/dqd), as MuJoCo's Euler does; `frames`: as `RigidBodyTree.kinematics`."""
        mass, bias = self._tree_terms(q, qd, frames)
        if damping_dt > 0:
            mass = mass + torch.diag_embed(damping_dt * self.tree.damping.to(q).expand_as(qd))
        if self.residual is not None:
            extra_mass, extra_bias = self.residual.mass_and_bias(q, qd, damping_dt)
            mass, bias = mass + extra_mass, bias + extra_bias
        return mass, bias

    def inverse_dynamics(self, q: Tensor, qd: Tensor, qdd: Tensor) -> Tensor:
        """tau = M qdd + c + g + d. (..., n)"""
        mass, bias = self._tree_terms(q, qd)
        tau = (mass @ qdd.unsqueeze(-1)).squeeze(-1) + bias
        if self.residual is not None:
            tau = tau + self.residual.inverse_dynamics(q, qd, qdd)
        return tau

    def forward_dynamics(self, q: Tensor, qd: Tensor, tau: Tensor) -> Tensor:
        """qdd = M^-1 (tau - c - g - d). (..., n)"""
        mass, bias = self.mass_and_bias(q, qd)
        return cholesky_solve(torch.linalg.cholesky_ex(mass).L, tau - bias)

    @torch.no_grad()
    def joint_stiffness(self, q: Tensor, step: float = 1e-3) -> Tensor:
        """The tree's springs plus the residual potential's slope along each hinge or slide,
        d g_res,j / d q_j by central differences of `step` on its coordinate, the median over
        configurations q (S, nq). (nv,)"""
        tree = self.tree
        stiffness = tree.spring_stiffness().to(q).clone()
        if self.residual is None:
            return stiffness
        zero = torch.zeros(*q.shape[:-1], tree.nv, dtype=q.dtype, device=q.device)
        for v in torch.nonzero(tree.scalar).flatten().tolist():
            index = int(tree.spring_q[v])
            up, down = q.clone(), q.clone()
            up[..., index] += step
            down[..., index] -= step
            slope = (self.residual.terms(up, zero).gravity[..., v]
                     - self.residual.terms(down, zero).gravity[..., v]) / (2 * step)  # fmt: skip
            stiffness[v] += slope.median()
        return stiffness

    def terms(self, q: Tensor, qd: Tensor) -> LagrangianTerms:
        """Every term at (q, qd) (the residual's added where there is one)."""
        kin = self.tree.kinematics(q)
        mass = self.tree.mass_matrix(q, kin)
        coriolis, gravity = self.tree.coriolis(qd, kin), self.tree.gravity(q, kin)
        spring = self.tree.spring(q)
        dissipation = self.tree.damping.to(qd) * qd
        potential = self.tree.potential_energy(q)
        if self.residual is not None:
            extra = self.residual.terms(q, qd)
            mass, coriolis = mass + extra.mass_matrix, coriolis + extra.coriolis
            gravity, dissipation = gravity + extra.gravity, dissipation + extra.dissipation
            potential = potential + extra.potential_energy
        kinetic = 0.5 * (qd.unsqueeze(-2) @ mass @ qd.unsqueeze(-1)).squeeze(-1).squeeze(-1)
        return LagrangianTerms(
            mass_matrix=mass, cholesky=torch.linalg.cholesky(mass), coriolis=coriolis,
            gravity=gravity + spring, dissipation=dissipation, kinetic_energy=kinetic,
            potential_energy=potential,
        )  # fmt: skip


def tree_start(start: str, system: System, total_mass: float | None = None) -> TreeStart:
    """The tree's start a model config names: ``mjcf`` the file's own numbers, ``geometric``
    its geometry (at 1,000 kg/m^3, or scaled to `total_mass` kg), ``documented`` the
    documented wrong start (`documented_start`)."""
    if start == "mjcf":
        return TreeStart.of_model(system.mj_model())
    spec = mujoco.MjSpec.from_file(str(system.xml_path))
    make = geometric_start if start == "geometric" else documented_start
    return make(spec, total_mass)


def tree_root_inertia(tree: RigidBodyTree, system: System) -> tuple[float, ...]:
    """A free root's six diagonal inertias at qpos0 by the tree's own numbers (the system
    has a free root)."""
    q0 = torch.as_tensor(system.mj_model().qpos0, dtype=torch.float64)
    with torch.no_grad():
        diagonal = tree.mass_matrix(q0).diagonal()[:6]
    return tuple(float(v) for v in diagonal)
