"""A user's own env, model and planner, registered from a module outside the package.

The worked example `examples/slider` (its module, MJCF and YAML files) is copied to a
temporary folder, as a user's project would hold it, and used as docs/architecture.md tells
("How to add an env / a task / a model / a planner"): ``plugins=[...]`` imports the module,
``hydra.searchpath`` finds its YAML files.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from mbrl_delan.conf.builders import build_model, build_planner
from mbrl_delan.conf.checks import CONFIG_DIR, ConfigError, compose_config, validate_train_config
from mbrl_delan.conf.checks import CONFIGS as CONFIGS_ROOT
from mbrl_delan.conf.loop import env_parts
from mbrl_delan.envs import make_env_parts, make_real_env
from mbrl_delan.registry import ENVS, MODELS, PLANNERS, load_plugins
from mbrl_delan.systems.system import SLIDE

CONFIGS = str(CONFIG_DIR)
EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "slider"
PLUGIN = "examples.slider.slider_parts"  # the module, as its `plugins=[...]` entry names it
PARTS = ["env=slider", "model=linear", "planner=shooting"]


@pytest.fixture(scope="module")
def user_project(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A user's project in a temporary folder: the worked example's module, MJCF and YAML
    files (`examples/slider`), importable from it as `examples.slider.slider_parts`."""
    root = tmp_path_factory.mktemp("user_project")
    shutil.copytree(EXAMPLE, root / "examples" / "slider")
    sys.path.insert(0, str(root))
    yield root
    sys.path.remove(str(root))


def _conf(root: Path) -> str:
    return f"hydra.searchpath=[file://{root / 'examples' / 'slider' / 'conf'}]"


def _compose(root: Path, *overrides: str):
    with initialize_config_dir(config_dir=CONFIGS, version_base=None):
        return compose("config", overrides=[_conf(root), *overrides])


def test_a_plugin_registers_an_env_a_model_and_a_planner(user_project: Path) -> None:
    load_plugins([PLUGIN])
    assert "slider" in ENVS and "linear" in MODELS and "shooting" in PLANNERS
    parts = make_env_parts("slider", episode_len=7)
    assert parts.system.nq == parts.system.nv == parts.system.nu == 1
    assert parts.task.episode_len == 7
    cfg = validate_train_config(_compose(user_project, f"plugins=[{PLUGIN}]", *PARTS))
    assert OmegaConf.get_type(cfg.model).__name__ == "LinearConfig"
    model = build_model(cfg.model, parts.system)
    planner = build_planner(cfg.planner, parts.system, torch.float32)
    assert type(model).__name__ == "LinearModel" and type(planner).__name__ == "RandomShooting"
    env = make_real_env("slider", seed=0, episode_len=5)
    assert env.rollout(5).shape == (5,)


def test_a_plugin_schema_types_its_group(user_project: Path) -> None:
    """The model's own schema checks its group: a type, a range, an unknown key."""
    base = [f"plugins=[{PLUGIN}]", *PARTS]
    for override, expected in (
        ("model.lr=-1", "model.lr=-1.0 is not valid; it must be a finite number > 0"),
        ("planner.init_std=abc", "planner.init_std: Value 'abc' of type 'str' could not"),
        ("+model.hiden=3", "model.hiden is not a config key"),
    ):
        with pytest.raises(ConfigError, match=expected):
            validate_train_config(_compose(user_project, *base, override))


def test_a_plugin_model_gets_compiled_planning_from_accel(user_project: Path) -> None:
    """``accel.*`` reaches any world model's planning objective: a plugin's schema need not
    name compile, cuda_graph or rollout_threads."""
    from mbrl_delan.conf.loop import build_policy

    overrides = [f"plugins=[{PLUGIN}]", *PARTS, "accel.compile=true", "accel.rollout_threads=1"]
    cfg = validate_train_config(_compose(user_project, *overrides))
    assert "compile" not in cfg.model
    parts = make_env_parts("slider")
    model = build_model(cfg.model, parts.system)
    policy = build_policy(cfg, parts.system, parts.task, model, torch.Generator())
    assert policy.objective_factory.compile is True
    assert policy.objective_factory.rollout_threads == 1


def test_a_task_option_the_env_registered_is_set_from_the_command_line(
    user_project: Path,
) -> None:
    """`register_env(options={"target": 1.0})` with no ``task:`` block in the env's YAML:
    ``env.task.target=0.3`` (and ``env.task={target: 0.3}``) reaches the task; a name the env
    does not take is a config error listing the ones it does."""
    base = [_conf(user_project), f"plugins=[{PLUGIN}]", *PARTS]
    for override in ("env.task.target=0.3", "env.task={target:0.3}"):
        cfg = validate_train_config(compose_config(CONFIG_DIR, [*base, override]))
        assert env_parts(cfg).task.target == 0.3
    default = validate_train_config(compose_config(CONFIG_DIR, base))
    assert env_parts(default).task.target == 1.0
    wrong = validate_train_config(compose_config(CONFIG_DIR, [*base, "env.task.traget=0.3"]))
    with pytest.raises(
        ConfigError, match=r"env 'slider' takes no task option traget \(it takes: target\)"
    ):
        env_parts(wrong)


def test_a_plugin_name_already_taken_is_refused(user_project: Path) -> None:
    load_plugins([PLUGIN])
    with pytest.raises(ValueError, match="model 'delan' is already registered"):
        MODELS.add("delan", lambda cfg, system: None)


def test_a_missing_plugin_module_is_a_config_error(user_project: Path) -> None:
    with pytest.raises(ConfigError, match="plugins: cannot import 'no_such_plugin'"):
        validate_train_config(_compose(user_project, "plugins=[no_such_plugin]"))


@pytest.mark.slow
def test_train_runs_a_loop_with_the_users_env_model_and_planner(
    user_project: Path, tmp_path: Path
) -> None:
    """The command a user runs: their env, model and planner through one round of the loop."""
    run_dir = tmp_path / "run"
    cmd = [
        sys.executable, "-m", "mbrl_delan.train", f"plugins=[{PLUGIN}]", _conf(user_project),
        *PARTS, "logger=none", "threads=1", "budget.oracle_episodes=1",
        "budget.final_eval_episodes=1", "fit.max_epochs=3", f"hydra.run.dir={run_dir}",
        "env.task.target=0.5",  # a task option the env registered, which its YAML does not list
    ]  # fmt: skip
    env = {**os.environ, "WANDB_MODE": "disabled"}
    # run from the project's folder, as its user would: `python -m` imports from there
    out = subprocess.run(
        cmd, capture_output=True, text=True, env=env, timeout=300, cwd=user_project
    )
    assert out.returncode == 0, out.stdout + out.stderr
    summary = json.loads((run_dir / "summary.json").read_text())
    assert (summary["env"], summary["model"], summary["planner"]) == (
        "slider", "linear", "shooting",
    )  # fmt: skip
    assert summary["iterations"] == 1 and summary["env_steps"] == 2 * 12
    assert OmegaConf.load(run_dir / "config.yaml").env.task == {"target": 0.5}
    assert 0.0 <= summary["eval_return_mean"] <= 12.0  # rewards lie in [0, 1]
    loaded = _load_run_in_a_fresh_interpreter(user_project, run_dir)
    assert "train LinearModel" in loaded and "plugin loaded by load_run: True" in loaded


# ------------------------------------------------- the fit, evaluate and load_run


def _fit_conf(root: Path) -> str:
    return f"hydra.searchpath=[file://{root / 'examples' / 'slider' / 'fit_conf'}]"


def _run_module(root: Path, *args: str) -> subprocess.CompletedProcess:
    """`python <args>` from the user's project folder (its modules importable from there)."""
    env = {**os.environ, "WANDB_MODE": "disabled"}
    return subprocess.run(
        [sys.executable, *args], capture_output=True, text=True, env=env, timeout=300, cwd=root
    )


def _load_run_in_a_fresh_interpreter(root: Path, run_dir: Path) -> str:
    """`load_run` where nothing imported the plugin: it must come from the run's config."""
    code = (
        "import sys; from mbrl_delan.runs import load_run; "
        f"r = load_run({str(run_dir)!r}); print(r.kind, type(r.model).__name__); "
        "print('plugin loaded by load_run:', 'examples.slider.slider_parts' in sys.modules)"
    )
    out = _run_module(root, "-c", code)
    assert out.returncode == 0, out.stdout + out.stderr
    return out.stdout


def test_a_plugin_registers_an_inverse_model_typed_by_its_schema(user_project: Path) -> None:
    from mbrl_delan.conf.fitting import FIT_CONFIG_DIR, validate_fit_config
    from mbrl_delan.registry import INVERSE_MODELS

    base = [f"plugins=[{PLUGIN}]", _fit_conf(user_project), "model=linear_inverse"]
    base += ["data=arrays", "data.path=x.npz", "data.joints=[slide]"]
    with initialize_config_dir(config_dir=str(FIT_CONFIG_DIR), version_base=None):
        cfg = compose("config", overrides=base)
        bad = compose("config", overrides=[*base, "+model.hidden=3"])
    validate_fit_config(cfg)
    assert "linear_inverse" in INVERSE_MODELS
    with pytest.raises(ConfigError, match="model.hidden is not a config key"):
        validate_fit_config(bad)


def test_a_plugin_registers_a_data_kind_typed_by_its_schema(user_project: Path) -> None:
    """The plugin's data kind: its group typed by its schema, its reader's splits on the
    slide's system with the torques its law gives, and a model on an MJCF tree refused on
    data that give none."""
    from mbrl_delan.conf.fitting import FIT_CONFIG_DIR, inverse_data, validate_fit_config

    base = [f"plugins=[{PLUGIN}]", _fit_conf(user_project), "data=slide_log"]
    with initialize_config_dir(config_dir=str(FIT_CONFIG_DIR), version_base=None):
        cfg = compose("config", overrides=[*base, "model=linear_inverse", "data.force=3"])
        unknown = compose("config", overrides=[*base, "+data.mass=2"])
        few = compose("config", overrides=[*base, "data.samples=5"])
        tree = compose("config", overrides=[*base, "model=white_box"])
    validate_fit_config(cfg)
    with pytest.raises(ConfigError, match="data.mass is not a config key"):
        validate_fit_config(unknown)
    with pytest.raises(ConfigError, match="data.samples=5"):
        validate_fit_config(few)
    with pytest.raises(ConfigError, match="kinematic tree .* data=slide_log does not give"):
        validate_fit_config(tree)
    data = inverse_data(cfg.data)
    assert set(data.splits) == {"train", "val", "test"} and data.system.layout.types == (SLIDE,)
    whole = torch.cat([data.splits[name] for name in ("train", "val", "test")])
    assert whole.shape[0] == 600
    tau = 2 * whole["qdd"] + 0.5 * whole["qd"] + 3.0
    torch.testing.assert_close(whole["tau"], tau)


@pytest.mark.slow
@pytest.mark.heavy
def test_fit_evaluate_and_load_run_with_the_users_inverse_model(
    user_project: Path, tmp_path: Path, run_main
) -> None:
    """The user's inverse-dynamics model through `fit` on the user's data kind (a slide with
    viscous friction and a constant force, where the model is exact), then `evaluate` on the
    run's own data in a fresh interpreter, which imports the plugin from the run's saved
    config (through `load_run`) to read them again, and `load_run` there."""
    from mbrl_delan.fit import main as fit_main

    run_dir = tmp_path / "fit"
    code, text = run_main(
        fit_main, f"plugins=[{PLUGIN}]", _fit_conf(user_project), "model=linear_inverse",
        "data=slide_log", "epochs=300", "lr=0.1", "logger=none", f"hydra.run.dir={run_dir}",
    )  # fmt: skip
    assert code == 0, text
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["model"] == "linear_inverse" and summary["test_r2"] > 0.999
    assert summary["data"] == "slide_log" and summary["force"] == 1.0
    code = (
        "import sys; from mbrl_delan.evaluate import main; from mbrl_delan.runs import load_run; "
        f"print('evaluate exit', main([{str(run_dir)!r}])); "
        "print('plugin loaded:', 'examples.slider.slider_parts' in sys.modules); "
        f"print(type(load_run({str(run_dir)!r}).model).__name__)"
    )
    out = _run_module(user_project, "-c", code)
    assert out.returncode == 0, out.stdout + out.stderr
    assert "evaluate exit 0" in out.stdout and "plugin loaded: True" in out.stdout, out.stdout
    assert "LinearInverse" in out.stdout


@pytest.mark.slow
@pytest.mark.heavy
def test_bench_times_the_users_planner(user_project: Path, tmp_path: Path) -> None:
    """`bench suite=planner` with the plugin's planner and its model as a case on the
    pendulum and on its own env (``pendulum_linear``, ``slider_linear``; no YAML among the
    loop's: their schemas' defaults) beside the suite's DeLaN case; an unregistered name is a
    config error."""
    out_file = tmp_path / "planner.jsonl"
    out = _run_module(
        user_project, "-m", "mbrl_delan.bench", "suite=planner", "quick=true",
        f"plugins=[{PLUGIN}]", "planners=[shooting]",
        "models=[pendulum_delan,pendulum_linear,slider_linear]", "torchrl=false",
        f"out={out_file}", f"hydra.run.dir={tmp_path / 'bench'}",
    )  # fmt: skip
    assert out.returncode == 0, out.stdout + out.stderr
    records = [json.loads(line) for line in out_file.read_text().splitlines()]
    latency = [r for r in records if r["metric"] == "plan_latency_ms"]
    assert {r["model"] for r in latency} == {"pendulum_delan", "pendulum_linear", "slider_linear"}
    assert all(r["planner"] == "shooting" for r in latency)
    assert all(r["value"] is None or r["value"] > 0 for r in latency)
    from mbrl_delan.bench import build_options

    with initialize_config_dir(config_dir=str(CONFIGS_ROOT / "bench"), version_base=None):
        unknown = compose("config", overrides=["suite=planner", "planners=[no_such_planner]"])
    with pytest.raises(ConfigError, match="'no_such_planner' is not a registered planner"):
        build_options(unknown)


def test_bench_realtime_plans_on_the_users_env_model_and_planner(
    user_project: Path, tmp_path: Path
) -> None:
    """`bench suite=realtime` on the plugin's env (its YAML found through the cases'
    overrides), planning with its planner on MuJoCo and on its model."""
    out_file = tmp_path / "realtime.jsonl"
    searchpath = f"hydra.searchpath=[file://{user_project / 'examples' / 'slider' / 'conf'}]"
    out = _run_module(
        user_project, "-m", "mbrl_delan.bench", "suite=realtime", "quick=true",
        f"plugins=[{PLUGIN}]", "tasks=[slider]", "models=[mujoco,linear]",
        f"overrides=['{searchpath}','planner=shooting']", f"out={out_file}",
        f"hydra.run.dir={tmp_path / 'bench'}",
    )  # fmt: skip
    assert out.returncode == 0, out.stdout + out.stderr
    records = [json.loads(line) for line in out_file.read_text().splitlines()]
    timed = [r for r in records if r["metric"] == "plan_ms_per_control_step"]
    assert {(r["task"], r["dynamics"], r["planner"]) for r in timed} == {
        ("slider", "mujoco", "shooting"), ("slider", "linear", "shooting"),
    }  # fmt: skip
    assert all(r["value"] > 0 for r in timed)


def test_evaluate_names_a_plugin_the_run_saved_that_cannot_be_imported(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A run whose saved plugin is gone: `evaluate` ends with one line naming the module,
    before it reads the checkpoint."""
    from mbrl_delan.evaluate import main as evaluate_main

    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "config.yaml").write_text("plugins: [no_such_plugin]\n")
    (run_dir / "checkpoint.pt").write_bytes(b"")
    assert evaluate_main([str(run_dir)]) == 2
    assert "plugins: cannot import 'no_such_plugin'" in caplog.text, caplog.text


def test_a_planner_without_warm_start_is_a_config_error_naming_it(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A registered builder whose planner lacks a method the planning policy calls (here
    `warm_start`, as a planner written from an older how-to would) is refused when it is
    built, before any episode: one config error naming the planner and the method."""
    from mbrl_delan.planners import CEMPlanner
    from mbrl_delan.registry import Entry

    class NoWarmStart:
        def __init__(self, inner: CEMPlanner) -> None:
            self.inner, self.horizon = inner, inner.horizon

        def __getattr__(self, name: str):
            if name == "warm_start":
                raise AttributeError(name)
            return getattr(self.inner, name)

    def build(cfg, system, dtype):
        return NoWarmStart(CEMPlanner(3, system.ctrl_low, system.ctrl_high))

    def build_plain(cfg, system, dtype):
        return CEMPlanner(3, system.ctrl_low, system.ctrl_high)

    PLANNERS.names()  # the package's own entries registered first
    monkeypatch.setitem(PLANNERS._entries, "no_warm_start", Entry("no_warm_start", build))
    monkeypatch.setitem(PLANNERS._entries, "plain", Entry("plain", build_plain))
    system = make_env_parts("pendulum").system
    named = r"planner=no_warm_start: its NoWarmStart has no warm_start, which the planning"
    with pytest.raises(ConfigError, match=named):
        build_planner(OmegaConf.create({"name": "no_warm_start"}), system, torch.float32)
    plain = build_planner(OmegaConf.create({"name": "plain"}), system, torch.float32)
    assert isinstance(plain, CEMPlanner)


def test_a_planner_class_without_warm_start_is_refused_when_registered(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """`register_planner(name, planner=Class)` (and `sampling_builder`'s builders, which
    carry their class) checks the Planner protocol at registration: a class without
    `warm_start` is a PluginError naming it, and through ``plugins=[...]`` one config error
    line, exit 2, before any run folder."""
    from mbrl_delan.registry import PluginError, register_planner

    class NoWarmStart:
        horizon = 3

        def initial_mean(self): ...
        def shift(self, mean, steps): ...
        def carry(self, result): ...
        def plan(self, problem, init, generator): ...

    monkeypatch.setattr(PLANNERS, "_entries", dict(PLANNERS._entries))  # leave the registry be
    with pytest.raises(PluginError, match=r"planner 'no_warm': its NoWarmStart has no warm_start"):
        register_planner("no_warm", planner=NoWarmStart)(lambda cfg, system, dtype: None)
    assert "no_warm" not in PLANNERS._entries
    module = tmp_path / "no_warm_plugin.py"
    module.write_text(
        "from mbrl_delan.registry import register_planner\n"
        "class Lazy:\n    def plan(self, problem, init, generator): ...\n"
        "register_planner('lazy', planner=Lazy)(lambda cfg, system, dtype: Lazy())\n"
    )
    run_dir = tmp_path / "run"
    out = _run_module(
        tmp_path, "-m", "mbrl_delan.train", "plugins=[no_warm_plugin]", "planner=cem",
        "logger=none", f"hydra.run.dir={run_dir}",
    )  # fmt: skip
    text = out.stdout + out.stderr
    assert out.returncode == 2 and "Traceback" not in text, text
    assert "has no initial_mean, shift, carry, warm_start, which the planning policy" in text
    assert not run_dir.exists()
