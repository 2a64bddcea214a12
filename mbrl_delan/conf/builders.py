"""World models and planners built from their config groups by their registry entries
(`build_model`, `build_planner`). The package's own register themselves beside their
classes (`models.delan_config`, `models.delan_ensemble`, `models.ensemble`,
`training.whitebox`; the planners in `planners`), imported with `mbrl_delan.conf`."""

from __future__ import annotations

import torch
from omegaconf import DictConfig, OmegaConf

from mbrl_delan.models.base import WorldModel
from mbrl_delan.planners.base import Planner
from mbrl_delan.registry import MODELS, PLANNERS, lacking
from mbrl_delan.rules import ConfigError
from mbrl_delan.systems.system import System


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
