"""`python -m mbrl_delan.bench suite=NAME out=FILE`: speed benchmarks as JSON Lines.

Each figure is one record `{"suite", "case", "metric", "value", "unit", "device", ...}`
appended to `out` as soon as it is measured (see `benchmarks/records.py`); the readable
table goes to the log at the end. `quick=true` runs tiny sizes (for tests and smoke runs).
Exit status 2 on a bad config value (an unknown suite included), naming the valid choices.
"""

from __future__ import annotations

import logging
import sys
from typing import Any

import hydra
import torch
from omegaconf import DictConfig, OmegaConf

from mbrl_delan.benchmarks import (
    HUMANOID_MODELS,
    HUMANOID_ORACLE_TASKS,
    ILQR_TASKS,
    ORACLE_PLANNERS,
    PLANNER_MODELS,
    SUITE_NAMES,
    SuiteOptions,
    TimingConfig,
    UnknownSuiteError,
    get_suite,
)
from mbrl_delan.benchmarks.records import RecordWriter, format_table
from mbrl_delan.config import ConfigError, check_device, exit_on_config_errors
from mbrl_delan.schema import PLANNER_SCHEMAS

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


def _positive_ints(name: str, values: Any) -> tuple[int, ...]:
    items = list(values) if OmegaConf.is_list(values) or isinstance(values, list) else [values]
    if not items or not all(
        isinstance(v, int) and not isinstance(v, bool) and v >= 1 for v in items
    ):
        raise ConfigError(f"{name}={values!r} is not valid; it must be a list of integers >= 1")
    return tuple(items)


def _optional_int(name: str, value: Any, minimum: int) -> int | None:
    """None (the suite's default) or an integer >= minimum."""
    if value is None:
        return None
    if not isinstance(value, int) or isinstance(value, bool) or value < minimum:
        raise ConfigError(
            f"{name}={value!r} is not valid; it must be null or an integer >= {minimum}"
        )
    return value


def _optional_positive_int(name: str, value: Any) -> int | None:
    """None (the suite's default) or an integer >= 1."""
    return _optional_int(name, value, 1)


def _optional_positive_ints(name: str, values: Any) -> tuple[int, ...] | None:
    """None (the suite's default) or a non-empty list of integers >= 1."""
    return None if values is None else _positive_ints(name, values)


def _optional_choices(
    name: str, values: Any, choices: tuple[str, ...], allow_empty: bool = False
) -> tuple[str, ...] | None:
    """None (the suite's default) or a list of names from `choices` (empty if allowed)."""
    if values is None:
        return None
    items = list(values) if OmegaConf.is_list(values) or isinstance(values, list) else [values]
    if (not items and not allow_empty) or not all(v in choices for v in items):
        empty = " (or [] for none)" if allow_empty else ""
        raise ConfigError(
            f"{name}={values!r} is not valid; use null or a list of: {', '.join(choices)}{empty}"
        )
    return tuple(items)


def _oracle_planner(value: Any, tasks: Any) -> str | None:
    """None (MPPI) or one of ORACLE_PLANNERS; iLQR only on tracking tasks (their residuals)."""
    if value is None:
        return None
    if value not in ORACLE_PLANNERS:
        raise ConfigError(
            f"oracle_planner={value!r} is not valid; use null or one of: "
            + ", ".join(ORACLE_PLANNERS)
        )
    others = [t for t in (HUMANOID_ORACLE_TASKS if tasks is None else tasks) if t not in ILQR_TASKS]
    if value == "ilqr" and others:
        raise ConfigError(
            f"oracle_planner=ilqr needs a tracking task's residuals: set oracle_tasks to a list of "
            f"{', '.join(ILQR_TASKS)} (it holds {', '.join(others)})"
        )
    return str(value)


def _overrides(name: str, values: Any) -> tuple[str, ...]:
    """Planner overrides ("planner.KEY=VALUE"), checked when the suite composes them."""
    items = [] if values is None else list(values)
    bad = [v for v in items if not (isinstance(v, str) and v.startswith("planner.") and "=" in v)]
    if bad:
        raise ConfigError(f"{name}={values!r} is not valid; give a list like ['planner.knots=3']")
    return tuple(items)


def _positive(name: str, value: Any) -> float:
    if not isinstance(value, int | float) or isinstance(value, bool) or value <= 0:
        raise ConfigError(f"{name}={value!r} is not valid; it must be a number > 0")
    return float(value)


def _compile_batch(values: Any) -> tuple[int, ...]:
    """An empty list (no compiled figures) or batch sizes >= 1."""
    if values is None or (OmegaConf.is_list(values) or isinstance(values, list)) and not values:
        return ()
    return _positive_ints("compile_batch", values)


def build_options(cfg: DictConfig) -> SuiteOptions:
    """Check the config and turn it into the suite's plain options (quick sizes applied)."""
    if cfg.suite not in SUITE_NAMES:
        raise ConfigError(
            f"suite={cfg.suite!r} is not a benchmark suite; valid suites: {', '.join(SUITE_NAMES)}"
        )
    values = {**OmegaConf.to_container(cfg, resolve=True), **(QUICK if cfg.quick else {})}
    if values["threads"] is not None:
        _positive_ints("threads", values["threads"])
    if not isinstance(values["warmup"], int) or values["warmup"] < 0:
        raise ConfigError(f"warmup={values['warmup']!r} is not valid; it must be an integer >= 0")
    return SuiteOptions(
        nv=_positive_ints("nv", values["nv"]),
        batch=_positive_ints("batch", values["batch"]),
        device=check_device(values["device"]),
        timing=TimingConfig(
            repeats=_positive_ints("repeats", values["repeats"])[0],
            min_time_s=_positive("min_time_s", values["min_time_s"]),
            warmup=values["warmup"],
        ),
        max_call_s=_positive("max_call_s", values["max_call_s"]),
        max_memory_bytes=int(_positive("max_memory_gb", values["max_memory_gb"]) * 1024**3),
        matmul_size=_positive_ints("matmul_size", values["matmul_size"])[0],
        humanoid=bool(values["humanoid"]),
        compile_batch=_compile_batch(values["compile_batch"]),
        quick=bool(values["quick"]),
        n_samples=_optional_positive_int("n_samples", values["n_samples"]),
        max_epochs=_optional_positive_int("max_epochs", values["max_epochs"]),
        planners=_optional_choices("planners", values["planners"], tuple(PLANNER_SCHEMAS)),
        models=_optional_choices(
            "models",
            values["models"],
            HUMANOID_MODELS if cfg.suite == "humanoid" else PLANNER_MODELS,
            allow_empty=cfg.suite == "humanoid",
        ),
        num_samples=_optional_positive_ints("num_samples", values["num_samples"]),
        horizons=_optional_positive_ints("horizons", values["horizons"]),
        iterations=_optional_positive_ints("iterations", values["iterations"]),
        torchrl=bool(values["torchrl"]),
        paired=bool(values["paired"]),
        rollout_threads=_optional_positive_int("rollout_threads", values["rollout_threads"]),
        compile_loop=bool(values["compile_loop"]),
        transitions=_optional_positive_ints("transitions", values["transitions"]),
        rollout_steps=_optional_positive_int("rollout_steps", values["rollout_steps"]),
        oracle_tasks=_optional_choices(
            "oracle_tasks", values["oracle_tasks"], HUMANOID_ORACLE_TASKS, allow_empty=True
        ),
        oracle_steps=_optional_positive_int("oracle_steps", values["oracle_steps"]),
        oracle_planner=_oracle_planner(values["oracle_planner"], values["oracle_tasks"]),
        oracle_overrides=_overrides("oracle_overrides", values["oracle_overrides"]),
        seed=_optional_int("seed", values["seed"], 0),
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


@hydra.main(version_base="1.3", config_path="../configs", config_name="bench")
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
