"""The typed config: every bad value fails at start naming its key, in-process.

`config_error` composes and checks a config as ``python -m mbrl_delan.train`` does (Hydra's
composition against the schemas, then `validate_train_config`) and returns the one line the
command prints; `test_the_command_exits_2_and_writes_nothing` runs the command's own `main`.
"""

from __future__ import annotations

import typing
from dataclasses import fields, is_dataclass
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import DictConfig, OmegaConf, open_dict

from mbrl_delan import train as train_module
from mbrl_delan.conf.builders import build_planner
from mbrl_delan.conf.checks import (
    COMPOSE_ERRORS,
    CONFIG_DIR,
    ConfigError,
    compose_config,
    config_error_line,
    exit_on_config_errors,
    migrate,
    validate_train_config,
)
from mbrl_delan.conf.schema import TrainConfig
from mbrl_delan.envs import make_env_parts
from mbrl_delan.registry import MODELS, PLANNERS, Registry

CONFIGS = str(CONFIG_DIR)


def own(registry: Registry) -> list[str]:
    """The package's own names in `registry` (a plugin test in this process adds its own;
    a sampling planner's builder is made in the planners' module, its class is the user's)."""

    def home(name: str) -> str:
        build = registry[name].build
        return getattr(build, "planner", build).__module__

    return sorted(n for n in registry.names() if home(n).startswith("mbrl_delan."))


def compose_train(*overrides: str) -> DictConfig:
    with initialize_config_dir(config_dir=CONFIGS, version_base=None):
        return compose("config", overrides=list(overrides))


def config_error(*overrides: str) -> str | None:
    """The config error line of these overrides, or None when the config is valid."""
    try:
        validate_train_config(compose_train(*overrides))
    except (ConfigError, *COMPOSE_ERRORS) as err:
        return config_error_line(err)
    return None


def integer_keys(node: DictConfig, prefix: str = "") -> list[str]:
    """The full keys of the integer fields of a typed config, recursively."""
    schema = OmegaConf.get_type(node)
    hints = typing.get_type_hints(schema) if is_dataclass(schema) else {}
    keys = []
    for f in fields(schema) if is_dataclass(schema) else []:
        value = node.get(f.name)
        if isinstance(value, DictConfig):
            keys += integer_keys(value, f"{prefix}{f.name}.")
        elif int in typing.get_args(hints[f.name]) or hints[f.name] is int:
            keys.append(f"{prefix}{f.name}")
    return keys


@pytest.mark.parametrize(
    ("override", "expected"),
    [
        ("budget.iterations=1.5", "budget.iterations: Value '1.5' of type 'float'"),
        ("planner.num_samples=2.5", "planner.num_samples: Value '2.5' of type 'float'"),
        ("env.horizon=0", "env.horizon=0 is not valid; it must be a whole number >= 1"),
        ("budget.iteratons=3", "budget.iteratons is not a config key; did you mean iterations?"),
        ("+model.hiden=3", "model.hiden is not a config key; did you mean hidden?"),
        ("model.diag_shift=nan", "model.diag_shift=nan is not valid; it must be a finite"),
        ("planner.temperature=inf", "planner.temperature=inf is not valid"),
        ("planner=random", "Could not find 'planner/random'; choose one of: cem, icem, mppi"),
        ("model.integrator=rk5", "model.integrator='rk5' is not valid; choose one of: euler, rk4"),
        ("planner.discount=0", "planner.discount=0.0 is not valid; it must be a finite number > 0"),
        ("env.name=cheetah", "env.name='cheetah' is not valid; choose one of: pendulum,"),
        ("logger.mode=live", "logger.mode='live' is not valid; choose one of: offline, online"),
    ],
)
def test_a_bad_value_names_its_key(override: str, expected: str) -> None:
    line = config_error(override)
    assert line is not None and expected in line, line
    assert "\n" not in line


@pytest.mark.parametrize(
    ("group", "option"),
    [(None, None)]
    + [("model", name) for name in own(MODELS)]
    + [("planner", name) for name in own(PLANNERS)],
)
def test_a_float_for_any_integer_key_is_refused(group: str | None, option: str | None) -> None:
    """Every integer key of the schemas (of each model's and planner's group; of the rest with
    the defaults) given 2.5: one line naming that key."""
    chosen = [f"{group}={option}"] if group else []
    keys = integer_keys(validate_train_config(compose_train(*chosen)))
    if group:
        keys = [k for k in keys if k.startswith(f"{group}.")]
    else:
        keys = [k for k in keys if not k.startswith(("model.", "planner."))]
        assert {"budget.iterations", "env.horizon", "fit.batch_size", "seed"} <= set(keys)
    assert keys
    for key in keys:
        line = config_error(*chosen, f"{key}=2.5")
        assert line is not None and line.startswith(f"{key}:"), (key, line)


def test_the_defaults_and_every_group_option_are_valid() -> None:
    for model in own(MODELS):
        for planner in own(PLANNERS):
            assert config_error(f"model={model}", f"planner={planner}") is None


def test_migrate_moves_the_acceleration_keys_an_old_delan_config_held() -> None:
    """Runs saved before ``accel`` held its keys in the DeLaN's group: they move over, and a
    saved config of a model that never had them gets the defaults."""
    saved = OmegaConf.create(OmegaConf.to_container(compose_train("model=delan"), resolve=True))
    with open_dict(saved):
        del saved["accel"]
        saved.model.update(compile=True, cuda_graph=False, rollout_threads=2, compile_fit=True)
    typed = validate_train_config(migrate(saved))
    assert OmegaConf.to_container(typed.accel) == {
        "compile": True, "cuda_graph": False, "rollout_threads": 2, "compile_loop": True,
        "compile_fit": True,
    }  # fmt: skip
    assert "compile" not in typed.model
    other = OmegaConf.create(OmegaConf.to_container(compose_train("model=ensemble"), resolve=True))
    with open_dict(other):
        del other["accel"]
    assert validate_train_config(migrate(other)).accel.compile is False


def test_migrate_fills_keys_an_old_run_config_lacks() -> None:
    """A run saved before the keys existed resumes with the values it ran with."""
    cfg = compose_train("planner=mppi")
    saved = OmegaConf.create(OmegaConf.to_container(cfg, resolve=True))
    for key in ("smoothing", "risk"):
        del saved.planner[key]
    del saved["plugins"], saved.buffer["device"]
    typed = validate_train_config(migrate(saved))
    assert typed.planner.smoothing == 0.0 and typed.planner.risk == 0.0
    assert typed.buffer.device == "auto"
    assert list(typed.plugins) == []
    assert OmegaConf.get_type(typed) is TrainConfig


@pytest.mark.parametrize(
    "override", ["budget.iterations=1.5", "planner.num_samples=2.5", "env.horizon=0"]
)
def test_the_command_exits_2_and_writes_nothing(override: str, tmp_path: Path, run_main) -> None:
    run_dir = tmp_path / "run"
    code, text = run_main(train_module.main, override, f"hydra.run.dir={run_dir}")
    assert code == 2, text
    assert f"config error: {override.split('=')[0]}" in text and "Traceback" not in text
    assert not run_dir.exists()  # no run folder, no crash.json


def test_a_key_under_a_null_node_is_one_line(caplog) -> None:
    """OmegaConf fails with a bare AssertionError where an override's key lies under a typed
    node that is null (a schema's ``dict | None`` field, as a user's may have): one line
    naming the override, exit 2."""

    def _apply_overrides_to_config() -> None:  # Hydra's function's name, its local `override`
        override = SimpleNamespace(input_line="model.options.depth=3")  # noqa: F841
        raise AssertionError("Unexpected type for root: NoneType")

    with pytest.raises(SystemExit) as exited:
        exit_on_config_errors(_apply_overrides_to_config)
    assert exited.value.code == 2
    assert caplog.messages == [
        "config error: model.options.depth=3: a node on its path is null in this config (it "
        "is set only for another choice of its config group)"
    ]


def test_a_task_option_another_env_takes_is_one_line_and_writes_nothing(
    tmp_path: Path, run_main
) -> None:
    """env.task.clip belongs to env=cmu_track: on the pendulum it is one line naming the env
    and the options it takes, exit 2, no folder."""
    run_dir = tmp_path / "run"
    code, text = run_main(train_module.main, "env.task.clip=02_01", f"hydra.run.dir={run_dir}")
    assert code == 2 and "Traceback" not in text, text
    assert "env 'pendulum' takes no task option clip (it takes: none)" in text, text
    assert len(text.strip().splitlines()) <= 3, text
    assert not run_dir.exists()


@pytest.mark.parametrize("choice", ["env=base_env", "model=base_delan", "planner=base_mppi"])
def test_a_schema_is_not_an_option(choice: str, tmp_path: Path, run_main) -> None:
    """The schemas live outside the groups: naming one as an option is an unknown option
    (one line with the real choices, no schema among them) and writes nothing."""
    run_dir = tmp_path / "run"
    code, text = run_main(train_module.main, choice, f"hydra.run.dir={run_dir}")
    assert code == 2 and "Traceback" not in text, text
    group, option = choice.split("=")
    assert f"Could not find '{group}/{option}'; choose one of:" in text, text
    assert "base_" not in text.split("choose one of:")[1].splitlines()[0], text
    assert not run_dir.exists()


@pytest.mark.parametrize("name", ["cem", "icem", "mppi", "predictive"])
def test_a_planner_built_from_an_empty_group_holds_the_schemas_defaults(name: str) -> None:
    """Each built-in planner's settings are stated once: a group with only its name and
    horizon builds a planner whose settings are the schema's defaults, the same as the
    planner's own constructor gives, and the ones the train config composes for it."""
    system = make_env_parts("pendulum").system
    group = OmegaConf.create({"name": name, "horizon": 7})
    built = build_planner(group, system, torch.float32)
    schema = {f.name: f.default for f in fields(PLANNERS[name].schema)}
    held = {f.name: getattr(built.settings, f.name) for f in fields(built.Settings)}
    assert held == {key: schema[key] for key in held}
    direct = type(built)(7, system.ctrl_low, system.ctrl_high)
    assert direct.settings == built.settings
    torch.testing.assert_close(direct.init_std, built.init_std)
    composed = validate_train_config(compose_config(CONFIG_DIR, [f"planner={name}"]))
    assert {key: composed.planner[key] for key in held} == held
