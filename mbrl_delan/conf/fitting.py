"""The fit's config (`python -m mbrl_delan.fit`): its checks before anything is built or
written (`validate_fit_config`), its data read by their registered kind (`inverse_data`;
`mbrl_delan.data.fit_kinds`) and its model built on the data's system
(`build_system_model`). The run itself, training and evaluation, is `mbrl_delan.fit_run`'s."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from omegaconf import DictConfig, OmegaConf, open_dict
from omegaconf.errors import OmegaConfBaseException

from mbrl_delan.conf.checks import (
    CONFIGS,
    ConfigError,
    check_device,
    check_ranges,
    load_config_plugins,
    schema_error_message,
)
from mbrl_delan.conf.fit_schema import FitRunConfig
from mbrl_delan.conf.inverse import (
    InverseContext,
    build_inverse_model,
    check_residual_start,
    typed_model,
)
from mbrl_delan.data.inverse_data import FitSystem, InverseData
from mbrl_delan.models.inverse import InverseDynamicsModel
from mbrl_delan.registry import FIT_DATA, INVERSE_MODELS, DataKind
from mbrl_delan.rules import check_choice
from mbrl_delan.systems.system import HINGE

# ${stem:${data.robot}} in run-dir names: a shipped arm's name, or an MJCF file's stem
OmegaConf.register_new_resolver("stem", lambda value: Path(str(value)).stem, replace=True)

FIT_CONFIG_DIR = CONFIGS / "fit"  # this entry point's YAML files


def data_kind(data: DictConfig) -> DataKind:
    """The registered kind of the data group (`mbrl_delan.registry.FIT_DATA`)."""
    return FIT_DATA[data.name].build


def typed_fit_config(cfg: DictConfig) -> DictConfig:
    """`cfg` merged into `FitRunConfig`, its data group into its kind's schema and its model
    group into the model's (`typed_model`): a wrong type or an unknown key is a ConfigError
    naming it."""
    check_choice("data.name", cfg.data.get("name"), FIT_DATA.names())
    check_choice("model.name", cfg.model.get("name"), INVERSE_MODELS.names())
    base = OmegaConf.structured(FitRunConfig)
    with open_dict(base):
        base.data = OmegaConf.structured(FIT_DATA[cfg.data.name].schema)
        base.model = {}
    try:
        typed = OmegaConf.merge(base, cfg)
    except OmegaConfBaseException as err:
        raise ConfigError(schema_error_message(err)) from err
    with open_dict(typed):
        typed.model = typed_model(cfg.model)
    return typed


def validate_fit_config(cfg: DictConfig) -> None:
    """Every value the fit entry point uses, checked before anything is built or written,
    once the config's ``plugins`` are loaded (their data kinds and models): each typed by
    its schema and within its range (`typed_fit_config`, `check_ranges`), then the rules
    between keys (`_check_fit_rules`)."""
    load_config_plugins(cfg)
    typed = typed_fit_config(cfg)
    check_ranges(typed)
    check_device(typed.device)
    _check_fit_rules(typed)


def _check_fit_rules(cfg: DictConfig) -> None:
    """The rules between the fit's keys, and the values a schema cannot type (the data
    kind's own rules, ``coulomb_lead``'s auto, a model on a tree the data do not give)."""
    kind = data_kind(cfg.data)
    if cfg.stop_on is not None:
        check_choice("stop_on", cfg.stop_on, kind.splits(cfg.data))
    if cfg.coulomb_lead not in (True, False, "auto"):
        raise ConfigError(
            f"coulomb_lead={cfg.coulomb_lead!r} is not valid; it must be true, false or auto"
        )
    if "start_level" in cfg.model and "diag_shift" in cfg.model:
        check_residual_start(cfg.model)
    kind.check(cfg.data)
    no_tree = kind.no_tree(cfg.data)
    if getattr(INVERSE_MODELS[cfg.model.name].schema, "needs_tree", False) and no_tree:
        raise ConfigError(f"model={cfg.model.name} {no_tree}")


def inverse_data(data: DictConfig) -> InverseData:
    """The splits and system the data group describes, read by its kind."""
    return data_kind(data).read(data)


def build_system_model(cfg: DictConfig, system: FitSystem) -> InverseDynamicsModel:
    """`build_inverse_model` of a fit config (``model``, ``loss``, ``translation_invariant``,
    ``periodic_hinges``, ``friction_init``, ``coulomb``, ``coulomb_lead``) for a system."""
    layout = system.layout
    if cfg.get("periodic_hinges", False):  # every hinge's features (sin q, cos q)
        hinges = [t == HINGE for t in layout.types]
        layout = replace(
            layout,
            limited=tuple(lim and not h for lim, h in zip(layout.limited, hinges, strict=True)),
        )
    context = InverseContext(
        layout,
        cfg.loss.std_floor,
        cfg.get("translation_invariant", False),
        system.dof_parents,
        system.armature,
        system.mj_model,
        cfg.get("friction_init"),
        cfg.get("coulomb"),
        cfg.get("coulomb_lead", False),
        data_kind(cfg.data).friction(cfg.data),
    )
    return build_inverse_model(cfg.model, context)
