"""The package's world models and planners built from their config groups: the registry's
built-ins (`MODELS`: delan, tree, tree_delan, delan_ensemble, ensemble, white_box;
`PLANNERS`: cem, icem, predictive, mppi), `build_model` and `build_planner` for any
registered one, and the DeLaN `Structure` a config describes (`delan_structure`)."""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import fields, replace
from typing import Any

import mujoco
import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from mbrl_delan.conf.checks import ConfigError
from mbrl_delan.conf.schema import (
    MODEL_SCHEMAS,
    PLANNER_SCHEMAS,
)
from mbrl_delan.conf.structure import read_structure
from mbrl_delan.models.base import WorldModel
from mbrl_delan.models.contact import ContactModel, ContactPoints, JointLimits
from mbrl_delan.models.delan import DeLaN
from mbrl_delan.models.delan_ensemble import DeLaNEnsemble
from mbrl_delan.models.ensemble import GaussianEnsemble
from mbrl_delan.models.structure import Structure
from mbrl_delan.models.tree import (
    RigidBodyTree,
    TreeStart,
    documented_start,
    geometric_start,
)
from mbrl_delan.objectives.mujoco import PlanPhysics, mujoco_threads
from mbrl_delan.planners.base import Planner, SamplingPlanner
from mbrl_delan.planners.cem import CEMPlanner
from mbrl_delan.planners.icem import ICEMPlanner
from mbrl_delan.planners.mppi import MPPIPlanner
from mbrl_delan.planners.predictive import PredictiveSampling
from mbrl_delan.registry import MODELS, PLANNERS, lacking, register_planner
from mbrl_delan.systems.forward_kinematics import ForwardKinematics
from mbrl_delan.systems.system import FREE, System
from mbrl_delan.training.whitebox import IdentifyConfig, WhiteBoxModel

log = logging.getLogger(__name__)

PlannerBuilder = Callable[[DictConfig, System, torch.dtype], Planner]


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


def known_root(system: System) -> tuple[tuple[float, ...], float]:
    """A free root's six diagonal inertias at qpos0 (MuJoCo's M) and the body's weight m |g|
    from the system's MJCF; a ConfigError without a free root."""
    if not system.layout.types or system.layout.types[0] != FREE:
        raise ConfigError(f"model.known_root=true needs a free root; {system.name} has none")
    model = system.mj_model()
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    full = np.zeros((model.nv, model.nv))
    mujoco.mj_fullM(model, data, full)
    weight = float(model.body_mass.sum() * np.linalg.norm(model.opt.gravity))
    return tuple(float(v) for v in np.diag(full)[:6]), weight


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


def _delan_arguments(cfg: DictConfig, system: System) -> dict[str, Any]:
    """The constructor arguments a DeLaN and every member of a DeLaN ensemble share."""
    return dict(
        layout=system.layout,
        actuation=system.actuation.float(),
        control_dt=system.control_dt,
        structure=delan_structure(cfg, system),
        integrator=cfg.integrator,
        substeps=cfg.substeps,
        loss=cfg.loss,
        velocity_margin=cfg.velocity_margin,
    )


def build_model(cfg: DictConfig, system: System) -> WorldModel:
    """The world model named by ``cfg.name`` (the model group), built by its registry entry."""
    return MODELS[cfg.name].build(cfg, system)


def build_planner(cfg: DictConfig, system: System, dtype: torch.dtype) -> Planner:
    """The planner named by ``cfg.name`` (the planner group, typed by its entry's schema:
    what it does not set takes the schema's defaults), built by its registry entry; a planner
    without a method of the `Planner` protocol is a ConfigError naming it."""
    entry = PLANNERS[cfg.name]
    if entry.schema is not None:  # the group's values (interpolations resolved in its config)
        values = OmegaConf.to_container(cfg, resolve=True)
        cfg = OmegaConf.merge(OmegaConf.structured(entry.schema), values)
    planner = entry.build(cfg, system, dtype)
    missing = lacking(planner)
    if not hasattr(planner, "horizon"):
        missing.append("horizon")
    if missing:
        raise ConfigError(
            f"planner={cfg.name}: its {type(planner).__name__} has no {', '.join(missing)}, "
            "which the planning policy calls (the Planner protocol, mbrl_delan/planners/base.py)"
        )
    return planner


@MODELS.register("delan", schema=MODEL_SCHEMAS["delan"])
def _delan(cfg: DictConfig, system: System) -> DeLaN:
    contact = None
    if cfg.contacts:
        implicit = cfg.contact_solve == "implicit"
        contact = ContactModel.from_mujoco(system.mj_model(), implicit=implicit)
    limits = JointLimits.from_mujoco(system.mj_model()) if cfg.joint_limits else None
    return DeLaN(**_delan_arguments(cfg, system), contact=contact, limits=limits)


@MODELS.register("tree_delan", schema=MODEL_SCHEMAS["tree_delan"])
@MODELS.register("tree", schema=MODEL_SCHEMAS["tree"])
def _tree(cfg: DictConfig, system: System) -> DeLaN:
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
    tree = RigidBodyTree.from_mujoco(system.mj_model(), tree_start(cfg, system),
                                     learn_springs=cfg.learn_springs)  # fmt: skip
    gravity = float(np.linalg.norm(system.mj_model().opt.gravity))
    weight = float(tree.total_mass().detach()) * gravity
    contact, limits = _floor_parts(cfg, system, weight)
    fixed: dict[str, Any] = {"residual": cfg.residual}
    if cfg.lagrangian_residual:
        fixed |= {"start_level": cfg.start_level, "friction_init": cfg.start_level}
    if cfg.known_root:
        fixed |= {"root_inertia": tree_root_inertia(tree, system), "root_weight": weight}
    arguments = _delan_arguments(cfg, system) | {"structure": delan_structure(cfg, system,
                                                                              **fixed)}  # fmt: skip
    return DeLaN(**arguments, contact=contact, limits=limits, tree=tree,
                 tree_residual=cfg.lagrangian_residual,
                 residual_penalty=cfg.residual_penalty)  # fmt: skip


def tree_start(cfg: DictConfig, system: System) -> TreeStart:
    """The tree's start a model config names (``start``, ``total_mass``)."""
    if cfg.start == "mjcf":
        return TreeStart.of_model(system.mj_model())
    spec = mujoco.MjSpec.from_file(str(system.xml_path))
    make = geometric_start if cfg.start == "geometric" else documented_start
    return make(spec, cfg.total_mass)


def tree_root_inertia(tree: RigidBodyTree, system: System) -> tuple[float, ...]:
    """A free root's six diagonal inertias at qpos0 by the tree's own numbers; a ConfigError
    without a free root."""
    if not system.layout.types or system.layout.types[0] != FREE:
        raise ConfigError(f"model.known_root=true needs a free root; {system.name} has none")
    q0 = torch.as_tensor(system.mj_model().qpos0, dtype=torch.float64)
    with torch.no_grad():
        diagonal = tree.mass_matrix(q0).diagonal()[:6]
    return tuple(float(v) for v in diagonal)


def _floor_parts(
    cfg: DictConfig, system: System, weight: float
) -> tuple[ContactModel | None, JointLimits | None]:
    """The contact model (its weight unit `weight`) and the joint limits a config asks for,
    where the system has a floor its geoms can touch (else none, logged)."""
    model = system.mj_model()
    contact = None
    if cfg.contacts:
        try:
            points = ContactPoints.from_mujoco(model)
        except ValueError as err:
            log.info("model.contacts: none on %s (%s)", system.name, err)
        else:
            contact = ContactModel(ForwardKinematics.from_mujoco(model),
                                   replace(points, weight=weight),
                                   implicit=cfg.contact_solve == "implicit")  # fmt: skip
    limits = JointLimits.from_mujoco(model) if cfg.joint_limits else None
    return contact, limits


@MODELS.register("delan_ensemble", schema=MODEL_SCHEMAS["delan_ensemble"])
def _delan_ensemble(cfg: DictConfig, system: System) -> DeLaNEnsemble:
    return DeLaNEnsemble(
        **_delan_arguments(cfg, system),
        ensemble_size=cfg.ensemble_size,
        propagation=cfg.propagation,
        bootstrap=cfg.bootstrap,
    )


@MODELS.register("ensemble", schema=MODEL_SCHEMAS["ensemble"])
def _ensemble(cfg: DictConfig, system: System) -> GaussianEnsemble:
    return GaussianEnsemble(
        layout=system.layout,
        nu=system.nu,
        control_dt=system.control_dt,
        ensemble_size=cfg.ensemble_size,
        hidden=cfg.hidden,
        layers=cfg.layers,
        activation=cfg.activation,
        propagation=cfg.propagation,
    )


@MODELS.register("white_box", schema=MODEL_SCHEMAS["white_box"])
def _white_box(cfg: DictConfig, system: System) -> WhiteBoxModel:
    model = WhiteBoxModel(
        system,
        physics=PlanPhysics(cfg.substeps, cfg.integrator),
        identify=IdentifyConfig(cfg.window, cfg.windows, cfg.iterations, cfg.fd_step),
        nthread=mujoco_threads(),
    )
    if cfg.start == "documented":
        model.set_multipliers(model.white.documented_start())
    return model


def sampling_builder(planner: type[SamplingPlanner]) -> PlannerBuilder:
    """The builder of a `SamplingPlanner` subclass (the package's and a user's): its
    `Settings` read from the planner group (typed by a schema that extends them)."""

    def build(cfg: DictConfig, system: System, dtype: torch.dtype) -> SamplingPlanner:
        settings = planner.Settings(**{f.name: cfg[f.name] for f in fields(planner.Settings)})
        return planner(cfg.horizon, system.ctrl_low, system.ctrl_high, settings, dtype)

    build.planner = planner  # type: ignore[attr-defined]  # checked when registered
    return build


SAMPLING_PLANNERS = {"cem": CEMPlanner, "icem": ICEMPlanner, "mppi": MPPIPlanner,
                     "predictive": PredictiveSampling}  # fmt: skip
for _name, _planner in SAMPLING_PLANNERS.items():  # as a user's are: checked when registered
    register_planner(_name, PLANNER_SCHEMAS[_name])(sampling_builder(_planner))
