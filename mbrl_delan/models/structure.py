"""What a DeLaN is made of, fixed when it is built: one frozen record, `Structure`.

`Structure.build(layout, actuation)` turns it into the mechanics (`LagrangianDynamics` over a
`LagrangianNetwork`) and the optional residual force. Two DeLaNs can share M, V and the
friction (`DeLaN.load_mechanics`) when their `Structure`s agree on `Structure.MECHANICS`.
`LagrangianConfig` is the config group's part every DeLaN model shares, `read_structure` the
one reader of such a group (train's ``model=delan`` and its kin, fit's ``model=delan`` and
``tree_delan``) into its `Structure`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import torch
from omegaconf import MISSING, DictConfig
from torch import Tensor

from mbrl_delan.models.base import ModelConfig
from mbrl_delan.models.features import QFeatures
from mbrl_delan.models.field import LagrangianNetwork, ResidualForce
from mbrl_delan.models.integrators import INTEGRATORS
from mbrl_delan.models.lagrangian import Dissipation, LagrangianDynamics
from mbrl_delan.rules import rule
from mbrl_delan.systems.system import BALL, FREE, HINGE, SLIDE, JointLayout


@dataclass(frozen=True)
class Structure:
    """The networks' shape and every structural option of a DeLaN.

    hidden, layers, activation: the trunk of `LagrangianNetwork` (and of the residual).
    diag_shift: added to L's softplus diagonal (> 0), so M stays positive definite.
    dissipation, coulomb: viscous friction, and Coulomb friction beside it (`Dissipation`).
    coulomb_lead: the Coulomb friction opposes qd + l qdd with a learned lead l per DoF (a
        soft friction constraint's, as MuJoCo's ``frictionloss``); not with `yaw_invariant`.
    coulomb_velocity: the Coulomb force's width, F tanh(qd / coulomb_velocity) (> 0).
    learn_coulomb_velocity: the width learned per DoF from `coulomb_velocity` (`Dissipation`),
        where there is a Coulomb term (`dissipation` and `coulomb`).
    translation_invariant: M and V's network do not see a free root's height; V gains an
        exact gravity term w z in it (`LagrangianNetwork`, ``heights``).
    yaw_invariant: a free root's heading and horizontal position enter nothing; M turns with
        the body about the vertical (`root_frame_jet`). Needs a free root first.
    still_first_order: coordinates held still in the data enter to first order about their
        held value (`LagrangianNetwork`, ``still_potential``).
    dof_parents: each DoF's parent DoF (MuJoCo's ``dof_parentid``): L gets the kinematic
        tree's sparsity. None: a dense L.
    armature: a known constant inertia per DoF in SI units (MuJoCo's ``dof_armature``),
        M = L L^T + diag(armature). None: none.
    inertia_scaling: M, V and the friction get units from the data (`DeLaN.fit_normalization`).
    diagonal_init: L's off-diagonal and V heads start at zero, the friction at 0.69 of its unit.
    friction_init: the friction's start in its unit instead (> 0; 1e-4: none until the data
        ask for it). None: as `diagonal_init` says.
    residual: a learned unstructured generalized force r(q, qd, a) beside B a (`ResidualForce`).
    root_inertia: what a user knows of a free root (the first joint): its six diagonal
        inertias at the rest pose (the total mass, then the body's rotational inertia about
        the root: MuJoCo's M at qpos0), which give its units with `inertia_scaling` where
        the data cannot (its generalized force is zero). None: from the data.
    root_weight: the body's weight m |g| (N); with `translation_invariant` the root height's
        potential starts at it (the data's mean root force is zero: contacts carry the body).
    spring_potential: V also holds a learned quadratic of the hinge and slide coordinates,
        1/2 q^T K q + b^T q with a full symmetric K (`LagrangianNetwork`, ``springs``): linear
        springs, coupled ones too, that the MJCF lacks.
    start_level: the mechanics start near zero, a residual Lagrangian beside a known rigid
        body (`models.tree.TreeDynamics`): L's diagonal at this share of its units (M at its
        square), V and L's other entries at 0 (`LagrangianNetwork.start_small`), the friction
        at `friction_init`. None: as `diagonal_init` says.
    """

    hidden: int = 64
    layers: int = 2
    activation: str = "softplus"
    diag_shift: float = 1e-3
    dissipation: bool = True
    coulomb: bool = True
    coulomb_lead: bool = False
    coulomb_velocity: float = 0.01
    learn_coulomb_velocity: bool = False
    translation_invariant: bool = False
    yaw_invariant: bool = False
    still_first_order: bool = False
    dof_parents: tuple[int, ...] | None = None
    armature: tuple[float, ...] | None = None
    inertia_scaling: bool = False
    diagonal_init: bool = False
    friction_init: float | None = None
    residual: bool = False
    root_inertia: tuple[float, ...] | None = None
    root_weight: float | None = None
    start_level: float | None = None
    spring_potential: bool = False

    # what M, V and the friction are made of: `load_mechanics` needs these equal
    MECHANICS: ClassVar[tuple[str, ...]] = (
        "hidden", "layers", "activation", "diag_shift", "dissipation", "coulomb", "coulomb_lead",
        "translation_invariant", "yaw_invariant", "still_first_order", "dof_parents", "armature",
        "spring_potential", "learn_coulomb_velocity",
    )  # fmt: skip

    def __post_init__(self) -> None:
        if self.dof_parents is not None:
            object.__setattr__(self, "dof_parents", tuple(int(p) for p in self.dof_parents))
        if self.armature is not None:
            values = torch.as_tensor(self.armature, dtype=torch.float64).reshape(-1).tolist()
            object.__setattr__(self, "armature", tuple(values))
        if self.coulomb_lead and not (self.dissipation and self.coulomb):
            raise ValueError("coulomb_lead needs Coulomb friction (dissipation and coulomb)")
        if not (self.dissipation and self.coulomb):  # no Coulomb term: no width to learn
            object.__setattr__(self, "learn_coulomb_velocity", False)
        if self.coulomb_lead and self.yaw_invariant:
            raise ValueError("coulomb_lead acts in joint axes: not with yaw_invariant")
        if self.friction_init is not None and self.friction_init <= 0:
            raise ValueError(f"friction_init must be > 0, got {self.friction_init}")
        if self.root_inertia is not None:
            values = tuple(float(v) for v in self.root_inertia)
            if len(values) != 6 or min(values) <= 0:
                raise ValueError(f"root_inertia must be 6 values > 0, got {self.root_inertia!r}")
            object.__setattr__(self, "root_inertia", values)

    def differences(self, other: Structure, names: Sequence[str] = MECHANICS) -> list[str]:
        """The fields among `names` on which `other` differs from this one."""
        return [name for name in names if getattr(self, name) != getattr(other, name)]

    def build(
        self, layout: JointLayout, actuation: Tensor
    ) -> tuple[LagrangianDynamics, ResidualForce | None]:
        """The mechanics and the residual force (None without) of a system with `layout`
        and actuation B (nv, nu)."""
        if self.yaw_invariant and not (layout.types and layout.types[0] == FREE):
            raise ValueError("yaw_invariant needs a model whose first joint is a free root")
        n = layout.nv
        features = QFeatures(layout, yaw_invariant=self.yaw_invariant)
        heights = free_root_heights(layout) if self.translation_invariant else []
        own_features = bool(heights) or self.still_first_order
        network = LagrangianNetwork(
            QFeatures(
                layout,
                root_height=not heights,
                freeze_still=self.still_first_order,
                yaw_invariant=self.yaw_invariant,
            )
            if own_features
            else features,
            n,
            self.hidden,
            self.layers,
            self.activation,
            self.diag_shift,
            heights=heights,
            still_potential=self.still_first_order,
            dof_parents=self.dof_parents,
            root_frame=self.yaw_invariant,
            springs=joint_coordinates(layout) if self.spring_potential else (),
        )
        raw_init = 0.0 if self.diagonal_init else -4.0
        if self.friction_init is not None:  # softplus(raw) = friction_init
            raw_init = math.log(math.expm1(self.friction_init))
        dissipation = (
            Dissipation(
                n,
                coulomb=self.coulomb,
                coulomb_velocity=self.coulomb_velocity,
                raw_init=raw_init,
                lead=self.coulomb_lead,
                learn_velocity=self.learn_coulomb_velocity,
            )  # fmt: skip
            if self.dissipation
            else None
        )
        dynamics = LagrangianDynamics(
            field=network,
            dissipation=dissipation,
            actuation=actuation.to(torch.get_default_dtype()),
            rotational_dofs=rotational_dofs(layout),
            armature=_armature(self.armature, n),
        )
        if self.start_level is not None:
            network.start_small(self.start_level)
        elif self.diagonal_init:
            network.start_diagonal()
        if not self.residual:
            return dynamics, None
        nu = actuation.shape[-1]
        return dynamics, ResidualForce(features, n, nu, self.hidden, self.layers)


def free_root_heights(layout: JointLayout) -> list[tuple[int, int]]:
    """(q index, v index) of each free joint's height z (its world-frame z velocity)."""
    return [
        (qa + 2, va + 2)
        for jtype, qa, va in zip(layout.types, layout.qpos_adr, layout.dof_adr, strict=True)
        if jtype == FREE
    ]


def joint_coordinates(layout: JointLayout) -> list[tuple[int, int]]:
    """(q index, v index) of each hinge and slide."""
    return [
        (qa, va)
        for jtype, qa, va in zip(layout.types, layout.qpos_adr, layout.dof_adr, strict=True)
        if jtype in (HINGE, SLIDE)
    ]


def rotational_dofs(layout: JointLayout) -> Tensor:
    """(K, 3) velocity indices of the angular velocity of each ball and free joint."""
    rows = [
        [adr + (3 if jtype == FREE else 0) + k for k in range(3)]
        for jtype, adr in zip(layout.types, layout.dof_adr, strict=True)
        if jtype in (BALL, FREE)
    ]
    return torch.tensor(rows, dtype=torch.long) if rows else torch.zeros(0, 3, dtype=torch.long)


def _armature(armature: Sequence[float] | Tensor | None, n: int) -> Tensor | None:
    """A known inertia per DoF as a tensor (n,), >= 0; None stays None."""
    if armature is None:
        return None
    value = torch.as_tensor(armature, dtype=torch.get_default_dtype()).reshape(-1)
    if value.shape != (n,) or not bool(torch.isfinite(value).all()) or bool((value < 0).any()):
        raise ValueError(f"armature must be {n} finite values >= 0, got {armature!r}")
    return value


@dataclass
class LagrangianConfig(ModelConfig):
    """The config group's settings a DeLaN and the members of a DeLaN ensemble share: the
    `Structure` fields of the same name (`STRUCTURE_KEYS`), how the model steps and learns,
    and where its units come from."""

    hidden: int = rule(low=1)
    layers: int = rule(low=1)
    activation: str = rule(choices=("softplus", "tanh"))
    diag_shift: float = rule(low=0)
    integrator: str = rule(choices=INTEGRATORS)
    substeps: int = rule(low=1)
    loss: str = rule(choices=("forward", "inverse", "both"))
    dissipation: bool = MISSING
    coulomb: bool = MISSING
    velocity_margin: float = rule(low=1)
    residual: bool = MISSING
    inertia_scaling: bool = MISSING
    translation_invariant: bool = MISSING
    yaw_invariant: bool = MISSING
    tree_sparse: bool = MISSING
    still_first_order: bool = MISSING
    armature: bool = MISSING
    known_root: bool = MISSING  # a free root's inertia units and weight from the MJCF
    spring_potential: bool = False  # V also holds 1/2 q^T K q + b^T q of the hinges and slides


# the model-group keys that are `Structure` fields of the same name (where a group has them)
STRUCTURE_KEYS = (
    "hidden", "layers", "activation", "diag_shift", "dissipation", "coulomb", "coulomb_velocity",
    "still_first_order", "translation_invariant", "yaw_invariant", "inertia_scaling", "residual",
    "spring_potential", "learn_coulomb_velocity",
)  # fmt: skip


def read_structure(
    cfg: DictConfig,
    dof_parents: Sequence[int] | None,
    armature: Sequence[float] | None,
    **fixed: Any,
) -> Structure:
    """The `Structure` of the model group `cfg`: its `STRUCTURE_KEYS`, ``inertia_scaling``'s
    diagonal start, the tree `dof_parents` where ``tree_sparse`` and the robot's `armature`
    where ``armature`` (each None: none to give); `fixed`: fields set by the caller, over the
    group's (the fit's friction and invariance, a known root)."""
    values: dict[str, Any] = {key: cfg[key] for key in STRUCTURE_KEYS if key in cfg}
    values["diagonal_init"] = values.get("inertia_scaling", False)
    if cfg.get("tree_sparse", False) and dof_parents is not None:
        values["dof_parents"] = list(dof_parents)
    if cfg.get("armature", False) and armature is not None:
        values["armature"] = list(armature)
    return Structure(**(values | fixed))
