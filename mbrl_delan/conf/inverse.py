"""Fit's inverse-dynamics models built from their config group: `build_inverse_model`
builds any registered one (the package's, `mbrl_delan.models.inverse_config`, and a
plugin's: `mbrl_delan.registry.register_inverse_model`) on an `InverseContext`, from its
group typed by its schema (`typed_model`)."""

from __future__ import annotations

from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from mbrl_delan.conf.checks import ConfigError, schema_error_message
from mbrl_delan.models.inverse import InverseDynamicsModel
from mbrl_delan.models.inverse_config import (
    InverseContext,
    branches,
    check_residual_start,
)
from mbrl_delan.registry import INVERSE_MODELS

__all__ = ["InverseContext", "branches", "build_inverse_model", "check_residual_start",
           "typed_model"]  # fmt: skip


def typed_model(cfg: DictConfig) -> DictConfig:
    """The model group merged into the schema its registry entry gives (the built-ins' in
    `models.inverse_config`; a plugin's without one: as it is): keys a run saved before them lacks
    take the schema's defaults; a wrong type or an unknown key is a ConfigError naming it."""
    schema = INVERSE_MODELS[cfg.name].schema
    if schema is None:
        return cfg
    try:
        return OmegaConf.merge(OmegaConf.structured(schema), cfg)
    except OmegaConfBaseException as err:  # its keys are the group's: model.<key>
        raise ConfigError(f"model.{schema_error_message(err)}") from err


def build_inverse_model(cfg: DictConfig, context: InverseContext) -> InverseDynamicsModel:
    """The inverse-dynamics model ``cfg.name`` names (`INVERSE_MODELS`: the package's delan,
    tree_delan, mlp, ensemble and white_box, and a plugin's), built on `context` from its
    group typed by its schema (`typed_model`)."""
    return INVERSE_MODELS[cfg.name].build(typed_model(cfg), context)
