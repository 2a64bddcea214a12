"""Fit's inverse-dynamics models from their config group: the registry's built-ins (delan,
tree_delan, mlp, ensemble, white_box) and `build_inverse_model`, which builds any registered
one (a plugin's: `mbrl_delan.conf.registry.register_inverse_model`) on an `InverseContext`."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import mujoco
from omegaconf import DictConfig

from mbrl_delan.conf.checks import ConfigError
from mbrl_delan.conf.registry import INVERSE_MODELS, register_inverse_model
from mbrl_delan.models.inverse import (
    DeLaNInverse,
    InverseDynamicsModel,
    MLPEnsembleInverse,
    MLPInverse,
)
from mbrl_delan.models.rigid_body import WhiteBoxInverse, data_friction_law
from mbrl_delan.models.structure import Structure
from mbrl_delan.models.tree import RigidBodyTree, TreeStart
from mbrl_delan.systems.system import JointLayout


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
    None: the model group's ``coulomb``). `data_friction`: the friction kind the data were
    made with, where known (`mbrl_delan.systems.arms.FRICTION_KINDS`; data=excitation)."""

    layout: JointLayout
    std_floor: float
    translation_invariant: bool = False
    dof_parents: Sequence[int] | None = None
    armature: Sequence[float] | None = None
    mj_model: mujoco.MjModel | None = None
    friction_init: float | None = None
    coulomb: bool | None = None
    coulomb_lead: bool = False
    data_friction: str | None = None


def build_inverse_model(cfg: DictConfig, context: InverseContext) -> InverseDynamicsModel:
    """The inverse-dynamics model ``cfg.name`` names (`INVERSE_MODELS`: the package's delan,
    mlp, ensemble and white_box, and a plugin's), built on `context`."""
    return INVERSE_MODELS[cfg.name].build(cfg, context)


@register_inverse_model("white_box")
def _white_box(cfg: DictConfig, context: InverseContext) -> WhiteBoxInverse:
    if context.mj_model is None:
        raise ConfigError("model=white_box needs an MJCF of the robot (data.mjcf)")
    law = cfg.get("friction_law", "frictionloss")  # a run saved before the option: that law
    if law == "auto":
        law = data_friction_law(context.data_friction)
    return WhiteBoxInverse(
        context.mj_model, cfg.prior_scale, cfg.prior_weight, context.std_floor, law
    )


def _structure(cfg: DictConfig, context: InverseContext, **fixed: float) -> Structure:
    # a tree that does not branch, an arm's chain, gets the dense lower factor L L^T: the same
    # matrices, and the fit of the upper factor trains to a 7x larger torque error on arm2
    parents = context.dof_parents
    return Structure(
        hidden=cfg.hidden,
        layers=cfg.layers,
        activation=cfg.activation,
        diag_shift=cfg.diag_shift,
        dissipation=cfg.dissipation,
        coulomb=cfg.coulomb if context.coulomb is None else context.coulomb,
        coulomb_lead=context.coulomb_lead,
        translation_invariant=context.translation_invariant,
        still_first_order=cfg.still_first_order,
        dof_parents=parents if cfg.get("tree_sparse", False) and branches(parents) else None,
        armature=context.armature if cfg.get("armature", False) else None,
        friction_init=context.friction_init,
        **fixed,
    )


@register_inverse_model("delan")
def _delan(cfg: DictConfig, context: InverseContext) -> DeLaNInverse:
    return DeLaNInverse(context.layout, _structure(cfg, context), std_floor=context.std_floor)


@register_inverse_model("tree_delan")
def _tree_delan(cfg: DictConfig, context: InverseContext) -> DeLaNInverse:
    """The MJCF's kinematic tree with learned inertias (from the MJCF's times
    ``prior_scale``) under a DeLaN residual started at ``start_level``."""
    if context.mj_model is None:
        raise ConfigError("model=tree_delan needs an MJCF of the robot (data.mjcf)")
    own = TreeStart.of_model(context.mj_model)
    start = TreeStart(own.inertial * cfg.prior_scale, own.damping, own.armature)
    tree = RigidBodyTree.from_mujoco(context.mj_model, start)
    structure = _structure(cfg, context, start_level=cfg.start_level)
    return DeLaNInverse(context.layout, structure, std_floor=context.std_floor, tree=tree)


@register_inverse_model("mlp")
def _mlp(cfg: DictConfig, context: InverseContext) -> MLPInverse:
    return MLPInverse(
        context.layout,
        hidden=cfg.hidden,
        activation=cfg.activation,
        std_floor=context.std_floor,
        root_height=not context.translation_invariant,
    )


@register_inverse_model("ensemble")
def _ensemble(cfg: DictConfig, context: InverseContext) -> MLPEnsembleInverse:
    return MLPEnsembleInverse(
        context.layout,
        ensemble_size=cfg.ensemble_size,
        hidden=cfg.hidden,
        activation=cfg.activation,
        std_floor=context.std_floor,
        root_height=not context.translation_invariant,
    )
