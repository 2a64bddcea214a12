"""The one reader of a DeLaN model group (train's ``model=delan`` and its kin, fit's
``model=delan`` and ``tree_delan``) into the `Structure` it describes."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from omegaconf import DictConfig

from mbrl_delan.models.structure import Structure

# the model-group keys that are `Structure` fields of the same name (where a group has them)
STRUCTURE_KEYS = (
    "hidden", "layers", "activation", "diag_shift", "dissipation", "coulomb", "coulomb_velocity",
    "still_first_order", "translation_invariant", "yaw_invariant", "inertia_scaling", "residual",
    "spring_potential",
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
