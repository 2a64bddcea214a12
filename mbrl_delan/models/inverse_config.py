"""Fit's inverse-dynamics models' config groups (``python -m mbrl_delan.fit model=NAME``):
the package's delan, tree_delan, mlp, ensemble and white_box, each with the schema that types
its group and its builder on an `InverseContext`, registered in `mbrl_delan.registry`
(`INVERSE_MODELS`) when this module is imported; a plugin's register the same way
(`register_inverse_model`)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import ClassVar

import mujoco
from omegaconf import MISSING, DictConfig

from mbrl_delan.models.inverse import (
    MLP_ACTIVATIONS,
    DeLaNInverse,
    MLPEnsembleInverse,
    MLPInverse,
)
from mbrl_delan.models.rigid_body import FRICTION_LAWS, WhiteBoxInverse, data_friction_law
from mbrl_delan.models.structure import Structure, read_structure
from mbrl_delan.models.tangent_mlp import ACTIVATIONS as DELAN_ACTIVATIONS
from mbrl_delan.models.tree import RigidBodyTree, TreeStart, armature_start
from mbrl_delan.registry import register_inverse_model
from mbrl_delan.rules import ConfigError, rule
from mbrl_delan.systems.system import JointLayout


@dataclass
class InverseModelConfig:
    """What every fit model group has; a plugin's schema extends it. `needs_tree`: the model
    is built on the robot's MJCF tree, which the fit's data must give."""

    needs_tree: ClassVar[bool] = False
    name: str = MISSING


@dataclass
class MLPInverseConfig(InverseModelConfig):
    """``model=mlp``."""

    hidden: int = rule(low=1)
    activation: str = rule(choices=tuple(MLP_ACTIVATIONS))


@dataclass
class EnsembleInverseConfig(MLPInverseConfig):
    """``model=ensemble``."""

    ensemble_size: int = rule(low=1)


@dataclass
class DeLaNInverseConfig(InverseModelConfig):
    """``model=delan``; the ones a run saved before them lacks are defaulted to what it ran."""

    hidden: int = rule(low=1)
    layers: int = rule(low=1)
    activation: str = rule(choices=DELAN_ACTIVATIONS)
    diag_shift: float = rule(low=0, above=True)
    dissipation: bool = MISSING
    coulomb: bool = MISSING
    coulomb_velocity: float = rule(0.01, low=0, above=True)
    learn_coulomb_velocity: bool = False  # the width learned per joint from coulomb_velocity
    still_first_order: bool = MISSING
    spring_potential: bool = False
    tree_sparse: bool = False
    armature: bool = False
    compile_fit: bool = False


@dataclass
class TreeDeLaNInverseConfig(DeLaNInverseConfig):
    """``model=tree_delan``; `start_level` above `diag_shift` (`check_residual_start`)."""

    needs_tree: ClassVar[bool] = True

    prior_scale: float = rule(low=0, above=True)
    start_level: float = rule(low=0, above=True)
    armature_start: float = rule(0.0, low=0)


@dataclass
class WhiteBoxInverseConfig(InverseModelConfig):
    """``model=white_box`` (a run saved before `friction_law`: frictionloss)."""

    needs_tree: ClassVar[bool] = True

    prior_scale: float = rule(low=0, above=True)
    prior_weight: float = rule(low=0)
    friction_law: str = rule("frictionloss", choices=("auto", *FRICTION_LAWS))


def check_residual_start(cfg: DictConfig) -> None:
    """The rule between a residual's keys (tree_delan's): its M starts above its floor."""
    if cfg.start_level <= cfg.diag_shift:
        raise ConfigError(
            f"model.start_level={cfg.start_level} is not valid; it must be > model.diag_shift"
            f"={cfg.diag_shift} (the residual's M starts above its floor)"
        )


def branches(dof_parents: Sequence[int] | None) -> bool:
    """Whether a kinematic tree (each DoF's parent, -1 for none) branches: only then does
    tree sparsity leave entries of M out (a chain couples every pair of DoFs)."""
    if dof_parents is None:
        return False
    parents = list(dof_parents)
    return len(set(parents)) < len(parents)


@dataclass(frozen=True)
class InverseContext:
    """What an inverse-dynamics model is built on, beside its config group: the joints
    (`layout`), the loss's per-DoF torque-std floor and the fit's settings for DeLaN-like
    models. `translation_invariant`: no model sees the root's position (DeLaN keeps gravity's
    exact w z potential in its height). `dof_parents`: the kinematic tree (DeLaN's
    ``model.tree_sparse``). `armature`: the model's ``dof_armature`` (DeLaN's
    ``model.armature``). `mj_model`: the robot's MJCF (the white box's structure).
    `friction_init`, `coulomb`, `coulomb_lead`: DeLaN's friction (`Structure`; `coulomb`
    None: the model group's ``coulomb``; `coulomb_lead` may be "auto": `lead`).
    `data_friction`: the friction kind the data were made with, where known
    (`mbrl_delan.systems.arms.FRICTION_KINDS`; data=excitation)."""

    layout: JointLayout
    std_floor: float
    translation_invariant: bool = False
    dof_parents: Sequence[int] | None = None
    armature: Sequence[float] | None = None
    mj_model: mujoco.MjModel | None = None
    friction_init: float | None = None
    coulomb: bool | None = None
    coulomb_lead: bool | str = False
    data_friction: str | None = None

    @property
    def lead(self) -> bool:
        """`coulomb_lead` resolved. "auto": a lead for data MuJoCo's joints made (friction
        none or its soft ``frictionloss``), none for sign(qd) friction or a robot's logs (a
        lead learned on sign(qd) friction leaks into M: 4.2% against 0.8%, light6)."""
        if self.coulomb_lead == "auto":
            return self.data_friction in ("none", "frictionloss")
        return bool(self.coulomb_lead)


@register_inverse_model("white_box", schema=WhiteBoxInverseConfig)
def _white_box(cfg: DictConfig, context: InverseContext) -> WhiteBoxInverse:
    if context.mj_model is None:
        raise ConfigError("model=white_box needs an MJCF of the robot (data.mjcf)")
    law = cfg.friction_law
    if law == "auto":
        law = data_friction_law(context.data_friction)
    return WhiteBoxInverse(
        context.mj_model, cfg.prior_scale, cfg.prior_weight, context.std_floor, law
    )


def _structure(cfg: DictConfig, context: InverseContext, **fixed: float) -> Structure:
    # a tree that does not branch, an arm's chain, gets the dense lower factor L L^T: the same
    # matrices, and the fit of the upper factor trains to a 7x larger torque error on arm2
    parents = context.dof_parents if branches(context.dof_parents) else None
    return read_structure(
        cfg,
        parents,
        context.armature,
        coulomb=cfg.coulomb if context.coulomb is None else context.coulomb,
        coulomb_lead=context.lead,
        translation_invariant=context.translation_invariant,
        friction_init=context.friction_init,
        **fixed,
    )


@register_inverse_model("delan", schema=DeLaNInverseConfig)
def _delan(cfg: DictConfig, context: InverseContext) -> DeLaNInverse:
    return DeLaNInverse(context.layout, _structure(cfg, context), std_floor=context.std_floor)


@register_inverse_model("tree_delan", schema=TreeDeLaNInverseConfig)
def _tree_delan(cfg: DictConfig, context: InverseContext) -> DeLaNInverse:
    """The MJCF's kinematic tree with learned inertias (from the MJCF's times
    ``prior_scale``; an armature it does not give from ``armature_start``) under a DeLaN
    residual started at ``start_level``."""
    if context.mj_model is None:
        raise ConfigError("model=tree_delan needs an MJCF of the robot (data.mjcf)")
    own = TreeStart.of_model(context.mj_model)
    armature = armature_start(context.mj_model, cfg.prior_scale * cfg.armature_start)
    start = TreeStart(own.inertial * cfg.prior_scale, own.damping, armature)
    tree = RigidBodyTree.from_mujoco(context.mj_model, start)
    structure = _structure(cfg, context, start_level=cfg.start_level)
    return DeLaNInverse(context.layout, structure, std_floor=context.std_floor, tree=tree)


@register_inverse_model("mlp", schema=MLPInverseConfig)
def _mlp(cfg: DictConfig, context: InverseContext) -> MLPInverse:
    return MLPInverse(
        context.layout,
        hidden=cfg.hidden,
        activation=cfg.activation,
        std_floor=context.std_floor,
        root_height=not context.translation_invariant,
    )


@register_inverse_model("ensemble", schema=EnsembleInverseConfig)
def _ensemble(cfg: DictConfig, context: InverseContext) -> MLPEnsembleInverse:
    return MLPEnsembleInverse(
        context.layout,
        ensemble_size=cfg.ensemble_size,
        hidden=cfg.hidden,
        activation=cfg.activation,
        std_floor=context.std_floor,
        root_height=not context.translation_invariant,
    )
