"""`python -m mbrl_delan.bench suite=NAME out=FILE`: speed benchmarks as JSON Lines.

Each figure is one record `{"suite", "case", "metric", "value", "unit", "device", ...}`
appended to `out` as soon as it is measured (see `benchmarks/records.py`); the readable
table goes to the log at the end. `quick=true` runs tiny sizes (for tests and smoke runs).
Exit status 2 on a bad config value (an unknown suite included), naming the valid choices.
"""

from __future__ import annotations

import logging
import sys

import hydra
import torch
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from mbrl_delan.benchmarks import (
    FIDELITY_CASES,
    HUMANOID_MODEL_VARIANTS,
    HUMANOID_MODELS,
    HUMANOID_ORACLE_TASKS,
    ILQR_TASKS,
    OWN_ARM_MODELS,
    PLANNER_MODELS,
    REALTIME_DYNAMICS,
    SuiteOptions,
    TimingConfig,
    UnknownSuiteError,
    get_suite,
    plugin_case,
)
from mbrl_delan.benchmarks.records import RecordWriter, format_table
from mbrl_delan.conf.checks import (
    ConfigError,
    check_device,
    check_ranges,
    exit_on_config_errors,
    load_config_plugins,
    schema_error_message,
)
from mbrl_delan.conf.schema import MODEL_SCHEMAS, BenchConfig
from mbrl_delan.registry import ENVS, MODELS, PLANNERS

log = logging.getLogger("mbrl_delan.bench")

QUICK = {
    "nv": [2],
    "batch": [4],
    "repeats": 3,
    "min_time_s": 0.01,
    "warmup": 1,
    "matmul_size": 256,
    "compile_batch": [],
}


def _plugin_models() -> tuple[str, ...]:
    """The plugins' registered world models (suite realtime plans on them by name)."""
    return tuple(m for m in MODELS.names() if m not in MODEL_SCHEMAS)


def _plugin_cases() -> tuple[str, ...]:
    """Suite planner's cases of the plugins' models: ``<env>_<model>`` on every registered
    env (the pendulum's, a plugin's)."""
    return tuple(plugin_case(e, m) for e in ENVS.names() for m in _plugin_models())


def _models(values: list[str] | None, suite: str) -> tuple[str, ...] | None:
    """None (the suite's default) or the suite's own model cases (suites humanoid and
    fidelity: or none; suite realtime: the dynamics planned on)."""
    if values is None:
        return None
    humanoid = suite in ("humanoid", "fidelity")
    known = {
        "humanoid": HUMANOID_MODELS + HUMANOID_MODEL_VARIANTS,
        "realtime": REALTIME_DYNAMICS + _plugin_models(),
        "fidelity": FIDELITY_CASES,
        "own_arm": OWN_ARM_MODELS,
    }.get(suite, PLANNER_MODELS + _plugin_cases())
    if (not values and not humanoid) or any(v not in known for v in values):
        empty = " (or [] for none)" if humanoid else ""
        raise ConfigError(
            f"models={values!r} is not valid; use null or a list of: {', '.join(known)}{empty}"
        )
    return tuple(values)


def _check_lists(cfg: DictConfig) -> None:
    """The lists that must not be empty (the rules on their elements are the schema's)."""
    lists = ("nv", "batch", "planners", "num_samples", "horizons", "iterations", "transitions",
             "robots", "friction", "samples", "designs", "test_designs", "seeds")  # fmt: skip
    for name in lists:
        if cfg[name] is not None and len(cfg[name]) == 0:
            raise ConfigError(f"{name}=[] is not valid; give at least one value (or null)")


ORACLE_KEYS = ("planner.", "env.oracle_")  # what `oracle_overrides` may set


def _check_oracle(cfg: DictConfig) -> None:
    """iLQR only on tracking tasks (their residuals); overrides only of the planner group and
    the env's oracle physics."""
    others = [t for t in cfg.oracle_tasks or HUMANOID_ORACLE_TASKS if t not in ILQR_TASKS]
    if cfg.oracle_planner == "ilqr" and others:
        raise ConfigError(
            f"oracle_planner=ilqr needs a tracking task's residuals: set oracle_tasks to a list of "
            f"{', '.join(ILQR_TASKS)} (it holds {', '.join(others)})"
        )
    bad = [v for v in cfg.oracle_overrides if not (v.startswith(ORACLE_KEYS) and "=" in v)]
    if bad:
        raise ConfigError(
            f"oracle_overrides={list(cfg.oracle_overrides)!r} is not valid; give a list of "
            "planner.* or env.oracle_* overrides like ['planner.knots=3', 'env.oracle_substeps=2']"
        )


def typed_bench_config(cfg: DictConfig) -> DictConfig:
    """`cfg` typed by `BenchConfig` and checked; a `ConfigError` names the first bad key."""
    try:
        typed = OmegaConf.merge(OmegaConf.structured(BenchConfig), cfg)
    except OmegaConfBaseException as err:
        raise ConfigError(schema_error_message(err)) from err
    check_ranges(typed)
    _check_lists(typed)
    _check_oracle(typed)
    return typed


def build_options(cfg: DictConfig) -> SuiteOptions:
    """Check the config and turn it into the suite's plain options (quick sizes applied),
    once its ``plugins`` are loaded (their planners count among `planners`' choices)."""
    typed = typed_bench_config(cfg)
    load_config_plugins(typed)
    for option, registry in (("planners", PLANNERS), ("tasks", ENVS)):
        for name in typed[option] or ():
            if name not in registry:
                raise ConfigError(
                    f"{option}: {name!r} is not a registered {registry.family}; choose among: "
                    f"{', '.join(registry.names())} (a plugin's needs its module in plugins=[...])"
                )
    v = {**OmegaConf.to_container(typed, resolve=True), **(QUICK if typed.quick else {})}
    tuples = lambda name: None if v[name] is None else tuple(v[name])  # noqa: E731
    return SuiteOptions(
        nv=tuple(v["nv"]),
        batch=tuple(v["batch"]),
        device=check_device(v["device"]),
        timing=TimingConfig(repeats=v["repeats"], min_time_s=v["min_time_s"], warmup=v["warmup"]),
        max_call_s=v["max_call_s"],
        max_memory_bytes=int(v["max_memory_gb"] * 1024**3),
        matmul_size=v["matmul_size"],
        humanoid=v["humanoid"],
        compile_batch=tuple(v["compile_batch"]),
        quick=v["quick"],
        n_samples=v["n_samples"],
        max_epochs=v["max_epochs"],
        planners=tuples("planners"),
        models=_models(v["models"], typed.suite),
        num_samples=tuples("num_samples"),
        horizons=tuples("horizons"),
        iterations=tuples("iterations"),
        torchrl=v["torchrl"],
        paired=v["paired"],
        rollout_threads=v["rollout_threads"],
        compile_loop=v["compile_loop"],
        transitions=tuples("transitions"),
        rollout_steps=v["rollout_steps"],
        oracle_tasks=tuples("oracle_tasks"),
        oracle_steps=v["oracle_steps"],
        clips=tuples("clips"),
        oracle_planner=v["oracle_planner"],
        oracle_overrides=tuple(v["oracle_overrides"]),
        seed=v["seed"],
        data_run=v["data_run"],
        env=v["env"],
        save_models=v["save_models"],
        tasks=tuples("tasks"),
        overrides=tuple(v["overrides"]),
        seeds=tuples("seeds"),
        starts=v["starts"],
        push=v["push"],
        push_step=v["push_step"],
        runs=tuple(v["runs"]),
        robots=tuples("robots"),
        friction=tuples("friction"),
        samples=tuples("samples"),
        designs=tuples("designs"),
        test_designs=tuples("test_designs"),
    )


def run(cfg: DictConfig) -> RecordWriter:
    """Run the configured suite, appending each record to `cfg.out` as it is measured."""
    opts = build_options(cfg)
    if cfg.threads is not None:
        torch.set_num_threads(cfg.threads)
    suite = get_suite(cfg.suite)
    try:
        writer = RecordWriter(cfg.out)
    except OSError as err:
        raise ConfigError(f"out={cfg.out!r}: cannot append records there ({err})") from err
    log.info(
        "suite %s on %s, %d torch threads, nv %s, batch %s%s",
        cfg.suite,
        opts.device,
        torch.get_num_threads(),
        list(opts.nv),
        list(opts.batch),
        f", appending to {writer.path}" if writer.path else "",
    )
    for record in suite(opts):
        writer.write(record)
    log.info("suite %s:\n%s", cfg.suite, format_table(writer.records))
    return writer


@hydra.main(version_base="1.3", config_path="configs/bench", config_name="config")
def hydra_main(cfg: DictConfig) -> None:
    try:
        run(cfg)
    except (ConfigError, UnknownSuiteError) as err:
        log.error("config error: %s", err)
        sys.exit(2)


def main() -> None:
    """``python -m mbrl_delan.bench``: a config error, Hydra's included, exits 2 naming it."""
    exit_on_config_errors(hydra_main)


if __name__ == "__main__":
    main()
