"""DeLaN's config groups, ``model=delan``, ``model=tree`` and ``model=tree_delan``: their
schemas (`DeLaNConfig`, `TreeConfig`) and builders, registered in `mbrl_delan.registry`
when this module is imported, and the `Structure` a group describes on a system
(`delan_structure`)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from omegaconf import DictConfig

from mbrl_delan.models.contact import ContactModel, JointLimits, floor_parts
from mbrl_delan.models.delan import DeLaN, Stepping, TreePrior
from mbrl_delan.models.structure import LagrangianConfig, Structure, read_structure
from mbrl_delan.models.tree import RigidBodyTree, tree_root_inertia, tree_start
from mbrl_delan.registry import register_model
from mbrl_delan.rules import ConfigError, rule
from mbrl_delan.systems.system import System

TREE_STARTS = ("documented", "geometric", "mjcf")


@dataclass
class DeLaNConfig(LagrangianConfig):
    """``model=delan``: DeLaN's networks alone, with the structured contact model and the
    MJCF's joint limits where asked."""

    contacts: bool = False  # the structured contact model (`models/contact.py`)
    contact_solve: str = rule("implicit", choices=("implicit", "explicit"))
    joint_limits: bool = False  # the MJCF's joint ranges as implicit one-sided springs
    init_from: str | None = None


@dataclass
class TreeConfig(DeLaNConfig):
    """``model=tree`` and ``model=tree_delan``: the MJCF's kinematic tree with learned
    inertias, damping and armature (`models/tree.py`), with DeLaN's networks as a residual
    Lagrangian beside it where `lagrangian_residual` (tree_delan)."""

    start: str = rule("documented", choices=TREE_STARTS)
    total_mass: float | None = rule(None, low=0, above=True)  # kg; None: geometry at 1,000 kg/m^3
    learn_springs: bool = False  # each joint's stiffness and rest learned, from the MJCF's
    lagrangian_residual: bool = False
    start_level: float = rule(2e-3, low=0, above=True)  # the residual's L diagonal, of its unit
    residual_penalty: float = rule(0.0, low=0)  # x the residual's torque share in the loss


def require_free_root(system: System) -> None:
    """A ConfigError naming ``model.known_root`` where the system has no free root."""
    if not system.has_free_root:
        raise ConfigError(f"model.known_root=true needs a free root; {system.name} has none")


def known_root(system: System) -> tuple[tuple[float, ...], float]:
    """`System.free_root` (the MJCF's free-root inertias and weight), checked first."""
    require_free_root(system)
    return system.free_root()


def delan_structure(cfg: DictConfig, system: System, **fixed: Any) -> Structure:
    """The `Structure` a DeLaN model config (train's, or a mocap fit's read by the loop)
    describes on `system` (`read_structure`: ``tree_sparse`` and ``armature`` take the
    system's ``dof_parentid`` and ``dof_armature``, ``known_root`` its free root's inertias);
    `fixed` gives fields the config does not hold (the fit's ``translation_invariant``)."""
    model = system.mj_model()
    if cfg.get("known_root", False):
        root_inertia, root_weight = known_root(system)
        fixed = {"root_inertia": root_inertia, "root_weight": root_weight} | fixed
    return read_structure(cfg, model.dof_parentid.tolist(), model.dof_armature.tolist(), **fixed)


def structure_overrides(structure: Structure, names: Sequence[str]) -> list[str]:
    """The model-config overrides that give `structure`'s fields `names`."""
    flags = {"dof_parents": "tree_sparse", "armature": "armature"}
    overrides = []
    for name in names:
        value = getattr(structure, name)
        if name in flags:
            name, value = flags[name], value is not None
        overrides.append(f"model.{name}={str(value).lower() if isinstance(value, bool) else value}")
    return overrides


def delan_arguments(cfg: DictConfig, system: System) -> dict[str, Any]:
    """The constructor arguments a DeLaN and every member of a DeLaN ensemble share."""
    return dict(
        layout=system.layout,
        actuation=system.actuation.float(),
        control_dt=system.control_dt,
        structure=delan_structure(cfg, system),
        stepping=Stepping(
            cfg.integrator, cfg.substeps, cfg.loss, velocity_margin=cfg.velocity_margin
        ),  # fmt: skip
    )


@register_model("delan", schema=DeLaNConfig)
def build_delan(cfg: DictConfig, system: System) -> DeLaN:
    contact = None
    if cfg.contacts:
        implicit = cfg.contact_solve == "implicit"
        contact = ContactModel.from_mujoco(system.mj_model(), implicit=implicit)
    limits = JointLimits.from_mujoco(system.mj_model()) if cfg.joint_limits else None
    return DeLaN(**delan_arguments(cfg, system), contact=contact, limits=limits)


@register_model("tree_delan", schema=TreeConfig)
@register_model("tree", schema=TreeConfig)
def build_tree(cfg: DictConfig, system: System) -> DeLaN:
    """The MJCF's tree with learned inertias (`RigidBodyTree`) from `cfg.start`; the contact
    model and joint limits where the system has a floor; with ``lagrangian_residual``,
    DeLaN's networks beside it started near zero. What the tree's start knows stands in for
    the MJCF's inertial numbers wherever the DeLaN would read them (a free root's units and
    weight, the contact law's weight unit)."""
    if cfg.residual_penalty > 0 and not cfg.lagrangian_residual:
        raise ConfigError(
            f"model.residual_penalty={cfg.residual_penalty} penalises a residual Lagrangian: "
            "it needs model.lagrangian_residual=true (model=tree_delan)"
        )
    model = system.mj_model()
    start = tree_start(cfg.start, system, cfg.total_mass)
    tree = RigidBodyTree.from_mujoco(model, start, learn_springs=cfg.learn_springs)
    weight = float(tree.total_mass().detach()) * float(np.linalg.norm(model.opt.gravity))
    contact, limits = floor_parts(model, weight, cfg.contacts, cfg.contact_solve == "implicit",
                                  cfg.joint_limits)  # fmt: skip
    fixed: dict[str, Any] = {"residual": cfg.residual}
    if cfg.lagrangian_residual:
        fixed |= {"start_level": cfg.start_level, "friction_init": cfg.start_level}
    if cfg.known_root:
        require_free_root(system)
        fixed |= {"root_inertia": tree_root_inertia(tree, system), "root_weight": weight}
    arguments = delan_arguments(cfg, system) | {"structure": delan_structure(cfg, system,
                                                                             **fixed)}  # fmt: skip
    prior = TreePrior(tree, cfg.lagrangian_residual, cfg.residual_penalty)
    return DeLaN(**arguments, contact=contact, limits=limits, tree=prior)
