"""Config checking and building, for the entry points only.

Library code takes plain arguments; this module turns a Hydra config into those arguments
and rejects a bad value at start with a message that names it and lists what is valid.
"""

from __future__ import annotations

import difflib
import logging
import math
import os
import sys
from collections.abc import Callable, Sequence
from dataclasses import fields, is_dataclass
from pathlib import Path
from typing import Any, NoReturn

import torch
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from hydra.errors import HydraException, MissingConfigException
from omegaconf import DictConfig, OmegaConf, open_dict
from omegaconf.errors import ConfigAttributeError, ConfigKeyError, OmegaConfBaseException

from mbrl_delan import EXIT_INTERRUPTED
from mbrl_delan.conf.schema import ACCEL_KEYS, TrainConfig
from mbrl_delan.models.base import WorldModel
from mbrl_delan.registry import ENVS, MODELS, PLANNERS, PluginError, load_plugins
from mbrl_delan.rules import ConfigError, check_choice, field_rule
from mbrl_delan.stops import STOPPED, stop
from mbrl_delan.training.checkpoint import RunWriteError
from mbrl_delan.training.fit import FitConfig

log = logging.getLogger(__name__)

DTYPES = {"float32": torch.float32, "float64": torch.float64}


def refuse_used_run_dir(run_dir: Path, run_files: Sequence[str], instead: str) -> None:
    """A new run must not start in a folder that holds another run's `run_files` (they would
    be overwritten). Raises ConfigError naming the folder, the files found and `instead`
    (what to do), before the run writes anything. (Hydra itself has by then rewritten its
    record of the launch in ``.hydra/`` and opened the log, which gets the error.)"""
    found = [name for name in run_files if (run_dir / name).exists()]
    if found:
        raise ConfigError(
            f"{run_dir} already holds a run ({', '.join(found)}); {instead} "
            "(those files were left as they were)"
        )


# what Hydra's composition and OmegaConf raise for a bad command line or config file
COMPOSE_ERRORS = (HydraException, OmegaConfBaseException)


def config_error_line(err: BaseException) -> str:
    """One line for a config error: ours, OmegaConf's (the full key; the nearest names of an
    unknown key) or Hydra's (an unknown group option: the valid ones)."""
    cause = err.__cause__ if isinstance(err.__cause__, OmegaConfBaseException) else err
    if isinstance(cause, OmegaConfBaseException):
        return schema_error_message(cause)
    if isinstance(err, MissingConfigException) and err.options is not None:
        first = str(err).strip().splitlines()[0]
        return f"{first}; choose one of: {', '.join(err.options)}"
    return " ".join(str(err).split())


def exit_config_error(err: BaseException) -> NoReturn:
    """Stop with ``config error: <config_error_line(err)>`` and exit code 2."""
    stop("config error", config_error_line(err))


def exit_on_config_errors(hydra_main: Callable[[], Any]) -> Any:
    """Run a ``@hydra.main`` function; a config error, from Hydra's composition or from the
    checks before the run starts, ends the process with exit code 2 and one line naming it
    (Hydra alone prints several lines and exits 1), as does a run file that cannot be
    written (`RunWriteError`: the path and the reason), and Ctrl-C that the run did not handle
    itself (one line, exit 130). Other errors propagate unchanged."""
    sys.excepthook = sys.__excepthook__  # the start's one-line Ctrl-C (`mbrl_delan`) is over
    previous = os.environ.get("HYDRA_FULL_ERROR")
    os.environ["HYDRA_FULL_ERROR"] = "1"  # Hydra raises its errors instead of exiting 1
    try:
        return hydra_main()
    except (ConfigError, *COMPOSE_ERRORS) as err:
        exit_config_error(err)
    except AssertionError as err:
        line = _override_under_null(err)
        if line is None:
            raise
        exit_config_error(
            ConfigError(
                f"{line}: a node on its path is null in this config (it is set only for "
                "another choice of its config group)"
            )
        )
    except RunWriteError as err:
        stop("write error", err)
    except KeyboardInterrupt:
        stop(STOPPED, "the run's folder, if it was made, keeps what it wrote",
             EXIT_INTERRUPTED)  # fmt: skip
    finally:
        if previous is None:
            os.environ.pop("HYDRA_FULL_ERROR", None)
        else:
            os.environ["HYDRA_FULL_ERROR"] = previous


def _override_under_null(err: AssertionError) -> str | None:
    """The command-line override whose key OmegaConf could not set because a node on its
    path is null (an AssertionError from inside Hydra's `_apply_overrides_to_config`), else
    None: any other AssertionError is not a config error."""
    tb = err.__traceback__
    while tb is not None:
        if tb.tb_frame.f_code.co_name == "_apply_overrides_to_config":
            override = tb.tb_frame.f_locals.get("override")
            return getattr(override, "input_line", None) or "an override"
        tb = tb.tb_next
    return None


def build_fit_config(cfg: DictConfig) -> FitConfig:
    """`FitConfig` from ``cfg.fit``; a bad or unknown key is a `ConfigError` naming it."""
    values = OmegaConf.to_container(cfg.fit)
    assert isinstance(values, dict)
    known = {f.name for f in fields(FitConfig)}
    unknown = sorted(set(values) - known)
    if unknown:
        raise ConfigError(
            f"fit.{unknown[0]} is not a fit setting; known: {', '.join(sorted(known))}"
        )
    try:
        return FitConfig(**values)
    except (TypeError, ValueError) as err:
        raise ConfigError(f"fit settings are not valid: {err}") from err


def check_device(device: str) -> torch.device:
    try:
        dev = torch.device(device)
    except RuntimeError as err:
        raise ConfigError(f"device={device!r} is not valid; use cpu, cuda or cuda:N") from err
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"device={device!r} asked for CUDA, but torch sees no CUDA device here")
    if dev.type not in ("cpu", "cuda"):
        raise ConfigError(f"device={device!r} is not valid; use cpu, cuda or cuda:N")
    return dev


CONFIGS = Path(__file__).resolve().parents[1] / "configs"  # the YAML files, one dir per entry point
CONFIG_DIR = CONFIGS / "train"  # python -m mbrl_delan.train's


# an env's task options (``env.task``) are what it registered (`register_env(options=...)`),
# which its YAML need not list: an override of one adds or sets it (Hydra's ``++``), and the
# env refuses a name it does not take
TASK_OVERRIDES = ("env.task.", "env.task=")


def command_line_overrides(overrides: Sequence[str]) -> list[str]:
    """`overrides` with each plain ``env.task.<option>=`` (or ``env.task=``) one add-or-set,
    and each former name of `RENAMED` (``model=whitebox``) its current one, with a one-line
    notice (the former names have no config of their own: ``--help`` lists only the
    current ones)."""
    return [_current_name(f"++{o}" if o.startswith(TASK_OVERRIDES) else o) for o in overrides]


def _current_name(override: str) -> str:
    family, _, name = override.partition("=")
    current = RENAMED.get(family, {}).get(name)
    if current is None:
        return override
    log.warning("%s=%s is now %s=%s: read as that", family, name, family, current)
    return f"{family}={current}"


def compose_config(config_dir: Path, overrides: Sequence[str] = ()) -> DictConfig:
    """The config Hydra composes from ``config_dir/config.yaml`` with `overrides` (as on the
    command line, `command_line_overrides` applied), also inside a running Hydra app (its own Hydra
    is put back after)."""
    running = GlobalHydra.instance().hydra if GlobalHydra.instance().is_initialized() else None
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=str(config_dir), version_base="1.3"):
            return compose("config", overrides=command_line_overrides(overrides))
    finally:  # the running app's Hydra back (the context set a new GlobalHydra instance)
        GlobalHydra.instance().clear()
        if running is not None:
            GlobalHydra.instance().initialize(running)


def compose_train_config(overrides: Sequence[str] = ()) -> DictConfig:
    """The training config of ``python -m mbrl_delan.train`` with `overrides`, typed and
    checked (`validate_train_config`): for code that builds parts as the loop does (the
    benchmarks)."""
    return validate_train_config(compose_config(CONFIG_DIR, overrides))


# keys added after runs were first saved, with the value a run saved without them used
MIGRATIONS: dict[str, Any] = {
    "plugins": [],
    "video": False,
    "budget.oracle_planner": "same",
    "budget.env_steps": None,  # runs ended after `iterations` rounds only
    "env.env_steps": None,
    "env.eval_episodes": 2,
    "buffer.device": "auto",
    "buffer.device_fraction": 0.5,
    "planner.risk": 0.0,
    "planner.smoothing": 0.0,  # MPPI without it: white noise
    "planner.min_samples": None,
    "planner.return_best": False,
    "planner.knots": None,
    "planner.interpolation": "linear",
    "model.init_from": None,
    "model.yaw_invariant": False,
    "model.contacts": False,
    "model.contact_solve": "explicit",  # one law for every point, stepped as a force
    "model.known_root": False,
    "env.model_known_root": False,
    "model.joint_limits": False,
    "env.oracle_substeps": None,  # the oracle planned on the env's own physics
    "env.oracle_integrator": None,
    "env.oracle_horizon": None,  # the iLQR oracle planned over the planner's horizon
    "env.plan_speed": None,  # the balance cost's target speed was the task's
    "model.residual_penalty": 0.0,  # a tree residual fitted without the penalty
    "model.learn_springs": False,  # the tree's springs were the MJCF's
    "model.spring_potential": False,  # the residual's potential was its network alone
    "budget.collect_envs": 1,
}


# keys a run saved before their removal has: their values are where they landed (the env's
# planner settings, now configs/train/tuning/, in the planner group)
REMOVED = ("env.mppi_temperature", "env.mppi_noise_std", "env.mppi_smoothing", "env.mppi_samples",
           "env.mppi_iterations", "env.plan_knots", "env.plan_interpolation")  # fmt: skip
# keys that moved: where a run saved before the move had them -> where they are now
MOVED = {f"model.{key}": f"accel.{key}" for key in ACCEL_KEYS}
# names that changed: family -> {former name: name}; a config with a former one runs as the
# name, with a one-line notice
RENAMED = {"model": {"whitebox": "white_box"}}


def renamed(cfg: DictConfig) -> DictConfig:
    """`cfg` with each former name of `RENAMED` (``model=whitebox``) read as its current one,
    logging a one-line notice; `cfg` itself is left as it is."""
    out = cfg
    for family, names in RENAMED.items():
        group = cfg.get(family)
        name = group.get("name") if isinstance(group, DictConfig) else None
        if name in names:
            log.warning("%s=%s is now %s=%s: read as that", family, name, family, names[name])
            out = out.copy() if out is cfg else out
            with open_dict(out):
                out[family].name = names[name]
    return out


def migrate(cfg: DictConfig) -> DictConfig:
    """A run's saved config with the keys added since it was saved (`MIGRATIONS`), where its
    model or planner has them (its schema lists them), filled with the values it ran with,
    the keys that moved (`MOVED`) in their new place and its names the current ones
    (`RENAMED`), without the keys removed since (`REMOVED`)."""
    out = renamed(cfg).copy()
    with open_dict(out):
        for key in REMOVED:
            group, _, leaf = key.rpartition(".")
            if isinstance(out.get(group), DictConfig):
                out[group].pop(leaf, None)
        for old, new in MOVED.items():
            group, _, leaf = old.rpartition(".")
            if leaf in (out.get(group) or {}):
                OmegaConf.update(out, new, out[group].pop(leaf), force_add=True)
        for key, value in MIGRATIONS.items():
            group, _, leaf = key.rpartition(".")
            node = out if not group else out.get(group)
            if node is None or leaf in node or not _has_field(out, group, leaf):
                continue
            node[leaf] = value
    return out


def _has_field(cfg: DictConfig, group: str, leaf: str) -> bool:
    """Whether the schema of `group` (model or planner: by its name) has the field `leaf`."""
    if group not in ("model", "planner"):
        return True
    registry = MODELS if group == "model" else PLANNERS
    name = cfg[group].get("name")
    schema = registry[name].schema if name in registry else None
    return schema is not None and leaf in {f.name for f in fields(schema)}


def load_config_plugins(cfg: DictConfig) -> None:
    """Import the modules of a config's ``plugins`` (train, fit, bench alike); one that
    cannot be imported is a ConfigError naming it and the cause."""
    try:
        load_plugins(cfg.get("plugins") or [])
    except PluginError as err:
        raise ConfigError(str(err)) from err


def validate_train_config(cfg: DictConfig) -> DictConfig:
    """The training config typed by its schemas and checked, before anything is built or
    written; a `ConfigError` names the first bad key. Returns the typed config.

    Loads the config's ``plugins`` first (their envs, models and planners), then: every group
    merged into its schema (`mbrl_delan.conf.schema`: types and unknown keys; a former name,
    `RENAMED`, read as the current one with a notice), every field's range
    (`check_ranges`: also NaN or inf in any float), the names against the registries, and the
    rules between keys (`_check_rules`).
    """
    load_config_plugins(cfg)
    typed = typed_train_config(renamed(cfg))
    check_ranges(typed)
    for family, registry in (("env", ENVS), ("model", MODELS), ("planner", PLANNERS)):
        check_choice(f"{family}.name", typed[family].name, registry.names())
    check_device(typed.device)
    _check_rules(typed)
    build_fit_config(typed)
    return typed


def typed_train_config(cfg: DictConfig) -> DictConfig:
    """`cfg` merged into `TrainConfig`, its model and planner into the schemas their registry
    entries give (an entry without a schema leaves its group untyped)."""
    base = OmegaConf.structured(TrainConfig)
    with open_dict(base):
        for family, registry in (("model", MODELS), ("planner", PLANNERS)):
            name = _get_name(cfg, family)
            schema = registry[name].schema if name in registry else None
            base[family] = OmegaConf.structured(schema) if schema else {}
    try:
        return OmegaConf.merge(base, cfg)
    except OmegaConfBaseException as err:
        raise ConfigError(schema_error_message(err)) from err


def _get_name(cfg: DictConfig, family: str) -> Any:
    group = cfg.get(family)
    if not isinstance(group, DictConfig) or "name" not in group:
        raise ConfigError(f"{family}.name is missing: choose a {family} ({family}=NAME)")
    return group.name


def schema_error_message(err: OmegaConfBaseException) -> str:
    """One line from OmegaConf's error: the full key, the value and why, and for an unknown key
    the nearest valid names."""
    key = getattr(err, "full_key", None) or "?"
    first = str(err).strip().splitlines()[0]
    if isinstance(err, ConfigKeyError | ConfigAttributeError):
        parent = getattr(err, "parent_node", None)
        known = [str(k) for k in parent] if isinstance(parent, DictConfig) else []
        return f"{key} is not a config key{_nearest(key.rsplit('.', 1)[-1], known)}"
    return f"{key}: {first}"


def check_ranges(cfg: DictConfig, prefix: str = "") -> None:
    """Every field of a typed node within its `rule` (`mbrl_delan.conf.schema`), every float finite,
    recursively; the first that is not is a `ConfigError` naming its full key."""
    schema = OmegaConf.get_type(cfg)
    rules = {f.name: field_rule(f.metadata) for f in fields(schema)} if is_dataclass(schema) else {}
    if rules:  # a key added with `+` to a typed group (Hydra lets it in)
        _refuse_unknown_keys(cfg, rules, prefix)
    for key in cfg:
        path = f"{prefix}{key}"
        value = cfg[key]
        if isinstance(value, DictConfig):
            check_ranges(value, f"{path}.")
            continue
        if value is None:
            continue
        rule = rules.get(str(key))
        if isinstance(value, float) and not math.isfinite(value) or rule and not rule.allows(value):
            why = rule.describe(value) if rule else "it must be a finite number"
            raise ConfigError(f"{path}={value!r} is not valid; {why}")


def _refuse_unknown_keys(cfg: DictConfig, known: Sequence[str], prefix: str) -> None:
    unknown = [str(k) for k in cfg if k not in known]
    if unknown:
        raise ConfigError(f"{prefix}{unknown[0]} is not a config key{_nearest(unknown[0], known)}")


def _nearest(key: str, known: Sequence[str]) -> str:
    """The hint "; did you mean a, b?" with the known keys nearest to `key`, or ""."""
    near = difflib.get_close_matches(key, list(known), n=3)
    return f"; did you mean {', '.join(near)}?" if near else ""


def _check_rules(cfg: DictConfig) -> None:
    """The rules between keys (single values are checked by `check_ranges`)."""
    if cfg.accel.cuda_graph and not str(cfg.device).startswith("cuda"):
        raise ConfigError(f"accel.cuda_graph=true needs device=cuda, got device={cfg.device}")
    _check_buffer(cfg)
    if cfg.planner.replan_every > cfg.planner.horizon:
        raise ConfigError(
            f"planner.replan_every={cfg.planner.replan_every} is not valid; it "
            f"must be <= planner.horizon={cfg.planner.horizon}"
        )
    if (
        cfg.model.get("propagation") == "tsinf"
        and "ensemble_size" in cfg.model
        and cfg.model.particles % cfg.model.ensemble_size
    ):
        raise ConfigError(
            f"model.particles={cfg.model.particles} is not valid with tsinf: it "
            f"must be a multiple of model.ensemble_size={cfg.model.ensemble_size}"
        )


def _check_buffer(cfg: DictConfig) -> None:
    """buffer.device: auto or a device; a memmap lives on disk (auto or cpu)."""
    buffer = cfg.buffer
    device = str(buffer.device)
    if device != "auto":
        try:
            check_device(device)
        except ConfigError as err:
            raise ConfigError(f"buffer.{err}; or use buffer.device=auto") from err
        if buffer.memmap and device != "cpu":
            raise ConfigError(
                f"buffer.device={device!r} is not valid with buffer.memmap=true: a memmap "
                "lives on disk (use auto or cpu)"
            )


def check_rollout_steps(cfg: DictConfig, model: WorldModel) -> None:
    """fit.rollout_steps > 1 needs a model that trains on windows of transitions (its
    `trains_on_windows`: a DeLaN with a forward loss term, any model that says so)."""
    if cfg.fit.rollout_steps > 1 and not model.trains_on_windows:
        raise ConfigError(
            f"fit.rollout_steps={cfg.fit.rollout_steps} is not valid with model={cfg.model.name}: "
            f"its {type(model).__name__} does not train on windows of transitions "
            "(WorldModel.trains_on_windows; a DeLaN does with model.loss=forward or both); use 1"
        )
