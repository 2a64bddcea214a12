"""Typed schemas of ``python -m mbrl_delan.bench``: the options every suite shares
(`BenchConfig`, ``configs/bench/config.yaml``) and each suite's own (``suite=NAME`` chooses
``configs/bench/suite/NAME.yaml``, typed by the suite's schema in `SUITE_SCHEMAS`).

A suite's YAML is in the global package, so its options stay top-level keys
(``suite=planner planners=[mppi]``), and a key of another suite is refused when Hydra composes
the config. Ranges are the fields' `rule`s; what a range cannot state (names a plugin
registers, keys that tie together) is the schema's `check`, run once the plugins are loaded.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any

from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from mbrl_delan.conf.bench_names import (
    FIDELITY_CASES,
    FIDELITY_ENVS,
    HUMANOID_MODEL_VARIANTS,
    HUMANOID_MODELS,
    HUMANOID_ORACLE_TASKS,
    ILQR_TASKS,
    ORACLE_PLANNERS,
    OWN_ARM_DESIGNS,
    OWN_ARM_FRICTION,
    OWN_ARM_MODELS,
    OWN_ARM_ROBOTS,
    OWN_ARM_STRUCTURES,
    PLANNER_MODELS,
    REALTIME_DYNAMICS,
    plugin_case,
)
from mbrl_delan.conf.checks import ConfigError, check_ranges, schema_error_message
from mbrl_delan.registry import ENVS, MODELS, PLANNERS, Registry
from mbrl_delan.rules import rule


@dataclass
class SuiteConfig:
    """The options of one suite: the fields of its YAML but ``suite``."""

    def check(self) -> None:
        """The rules a field's range cannot state; a `ConfigError` names the key."""


@dataclass
class DelanSuiteConfig(SuiteConfig):
    nv: list[int] = rule(low=1, nonempty=True)
    batch: list[int] = rule(low=1, nonempty=True)
    compile_batch: list[int] = rule(low=1)
    matmul_size: int = rule(low=1)
    humanoid: bool = True


@dataclass
class IdentifySuiteConfig(SuiteConfig):
    """Suites identify and identify_humanoid."""

    n_samples: int | None = rule(None, low=1)
    max_epochs: int | None = rule(None, low=1)


@dataclass
class OverridesSuiteConfig(SuiteConfig):
    """Suite mocap (fit-config overrides)."""

    overrides: list[str] = field(default_factory=list)


@dataclass
class PlannerSuiteConfig(SuiteConfig):
    planners: list[str] | None = rule(None, nonempty=True)
    models: list[str] | None = rule(None, nonempty=True)
    num_samples: list[int] | None = rule(None, low=1, nonempty=True)
    horizons: list[int] | None = rule(None, low=1, nonempty=True)
    iterations: list[int] | None = rule(None, low=1, nonempty=True)
    torchrl: bool = True
    paired: bool = False
    rollout_threads: int | None = rule(None, low=1)
    compile_loop: bool = True

    def check(self) -> None:
        registered("planners", self.planners, PLANNERS)
        plugin_cases = [plugin_case(e, m) for e in ENVS.names() for m in plugin_models()]
        known("models", self.models, (*PLANNER_MODELS, *plugin_cases))


@dataclass
class HumanoidSuiteConfig(SuiteConfig):
    models: list[str] | None = rule(None, choices=HUMANOID_MODELS + HUMANOID_MODEL_VARIANTS)
    horizons: list[int] | None = rule(None, low=1, nonempty=True)
    transitions: list[int] | None = rule(None, low=1, nonempty=True)
    rollout_steps: int | None = rule(None, low=1)
    oracle_tasks: list[str] | None = rule(None, choices=HUMANOID_ORACLE_TASKS)
    oracle_steps: int | None = rule(None, low=1)
    clips: list[str] | None = None
    oracle_planner: str | None = rule(None, choices=ORACLE_PLANNERS)
    oracle_overrides: list[str] = field(default_factory=list)
    seed: int | None = rule(None, low=0)
    data_run: str | None = None

    def check(self) -> None:
        """iLQR only on tracking tasks (their residuals); overrides only of the planner group
        and the env's oracle physics."""
        others = [t for t in self.oracle_tasks or HUMANOID_ORACLE_TASKS if t not in ILQR_TASKS]
        if self.oracle_planner == "ilqr" and others:
            raise ConfigError(
                f"oracle_planner=ilqr needs a tracking task's residuals: set oracle_tasks to a "
                f"list of {', '.join(ILQR_TASKS)} (it holds {', '.join(others)})"
            )
        bad = [v for v in self.oracle_overrides if not (v.startswith(ORACLE_KEYS) and "=" in v)]
        if bad:
            raise ConfigError(
                f"oracle_overrides={self.oracle_overrides!r} is not valid; give a list of "
                "planner.* or env.oracle_* overrides like "
                "['planner.knots=3', 'env.oracle_substeps=2']"
            )


ORACLE_KEYS = ("planner.", "env.oracle_")  # what suite humanoid's `oracle_overrides` may set


@dataclass
class RealtimeSuiteConfig(SuiteConfig):
    tasks: list[str] | None = rule(None, nonempty=True)
    models: list[str] | None = rule(None, nonempty=True)
    oracle_steps: int | None = rule(None, low=1)
    seed: int | None = rule(None, low=0)
    overrides: list[str] = field(default_factory=list)
    load: int = rule(0, low=0)  # busy processes beside each timed case
    profile: bool = False  # learned models' cases also split their eager path into parts

    def check(self) -> None:
        registered("tasks", self.tasks, ENVS)
        known("models", self.models, (*REALTIME_DYNAMICS, *plugin_models()))


@dataclass
class RobustSuiteConfig(SuiteConfig):
    tasks: list[str] | None = rule(None, nonempty=True)
    overrides: list[str] = field(default_factory=list)
    oracle_steps: int | None = rule(None, low=1)
    seeds: list[int] | None = rule(None, low=0, nonempty=True)
    starts: int | None = rule(None, low=1)
    push: float | None = None
    push_step: int = rule(200, low=0)

    def check(self) -> None:
        registered("tasks", self.tasks, ENVS)


@dataclass
class FitArraysSuiteConfig(SuiteConfig):
    seed: int | None = rule(None, low=0)
    overrides: list[str] = field(default_factory=list)
    torque_noise: float = rule(0.0, low=0)  # the torques' noise: a share of each joint's RMS
    systems: list[str] | None = rule(None, choices=("arm2", "arm3"), nonempty=True)


@dataclass
class FidelitySuiteConfig(SuiteConfig):
    models: list[str] | None = rule(None, choices=FIDELITY_CASES)
    transitions: list[int] | None = rule(None, low=1, nonempty=True)
    oracle_steps: int | None = rule(None, low=1)
    seed: int | None = rule(None, low=0)
    data_run: str | None = None
    overrides: list[str] = field(default_factory=list)
    runs: list[str] = field(default_factory=list)
    env: str | None = rule(None, choices=FIDELITY_ENVS)
    save_models: str | None = None
    data_contacts: bool = True  # false: random episodes simulated without contacts (free fall)


@dataclass
class OwnArmSuiteConfig(SuiteConfig):
    robots: list[str] | None = rule(None, choices=OWN_ARM_ROBOTS, nonempty=True)
    friction: list[str] | None = rule(None, choices=OWN_ARM_FRICTION, nonempty=True)
    samples: list[int] | None = rule(None, low=1, nonempty=True)
    designs: list[str] | None = rule(None, choices=OWN_ARM_DESIGNS, nonempty=True)
    test_designs: list[str] | None = rule(None, choices=OWN_ARM_DESIGNS, nonempty=True)
    models: list[str] | None = rule(None, choices=OWN_ARM_MODELS, nonempty=True)
    structures: list[str] | None = rule(None, choices=OWN_ARM_STRUCTURES, nonempty=True)
    model_mjcf: str | None = None
    seed: int | None = rule(None, low=0)
    overrides: list[str] = field(default_factory=list)

    def check(self) -> None:
        if self.model_mjcf is not None and self.model_mjcf not in ("exact", "cad"):
            raise ConfigError(f"model_mjcf={self.model_mjcf!r} is not valid; choose exact or cad")


# each suite's options (``configs/bench/suite/NAME.yaml``); the suites' functions are
# `mbrl_delan.benchmarks.SUITES`, which names the same suites (a test checks it)
SUITE_SCHEMAS: dict[str, type[SuiteConfig]] = {
    "delan": DelanSuiteConfig,
    "identify": IdentifySuiteConfig,
    "mocap": OverridesSuiteConfig,
    "identify_humanoid": IdentifySuiteConfig,
    "planner": PlannerSuiteConfig,
    "humanoid": HumanoidSuiteConfig,
    "realtime": RealtimeSuiteConfig,
    "robust": RobustSuiteConfig,
    "fit_arrays": FitArraysSuiteConfig,
    "soak": SuiteConfig,
    "fidelity": FidelitySuiteConfig,
    "own_arm": OwnArmSuiteConfig,
}
SUITE_NAMES = tuple(SUITE_SCHEMAS)


@dataclass
class BenchConfig:
    """What every suite shares (``configs/bench/config.yaml``); `suite` chooses the group."""

    suite: str = rule(choices=SUITE_NAMES)
    out: str | None = None
    device: str = "cpu"
    threads: int | None = rule(None, low=1)
    quick: bool = False
    plugins: list[str] = field(default_factory=list)
    repeats: int = rule(low=1)
    min_time_s: float = rule(low=0, above=True)
    warmup: int = rule(low=0)
    max_call_s: float = rule(low=0, above=True)
    max_memory_gb: float = rule(low=0, above=True)


SHARED_KEYS = tuple(f.name for f in fields(BenchConfig))


def typed_bench_config(cfg: DictConfig) -> tuple[DictConfig, DictConfig]:
    """The shared keys of `cfg` typed by `BenchConfig` and the rest by the suite's schema, each
    within its ranges; a `ConfigError` names the first bad key."""
    shared = _typed(BenchConfig, OmegaConf.masked_copy(cfg, [k for k in SHARED_KEYS if k in cfg]))
    own = OmegaConf.masked_copy(cfg, [str(k) for k in cfg if k not in SHARED_KEYS])
    return shared, _typed(SUITE_SCHEMAS[shared.suite], own)


def check_suite_keys(overrides: list[str], suite: str) -> None:
    """A `ConfigError` for a plain ``key=value`` override that is neither a shared key nor
    an option of the suite chosen (``suite=NAME`` among `overrides`, else `suite`, the
    config's default), naming the suites that take it (Hydra alone says only that the key is
    not in the config)."""
    pairs = [o.split("=", 1) for o in overrides if "=" in o and o[0].isalpha()]
    chosen = next((v for k, v in reversed(pairs) if k == "suite"), suite)
    if chosen not in SUITE_SCHEMAS:
        return  # Hydra names the valid suites
    own = {f.name for f in fields(SUITE_SCHEMAS[chosen])}
    for key, _ in pairs:
        if "." in key or "/" in key or key in SHARED_KEYS or key in own:
            continue
        takers = [n for n, e in SUITE_SCHEMAS.items() if key in {f.name for f in fields(e)}]
        where = f"; it is an option of suite {', '.join(takers)}" if takers else ""
        raise ConfigError(f"{key} is not an option of suite {chosen}{where}")


def _typed(schema: type, cfg: DictConfig) -> DictConfig:
    try:
        typed = OmegaConf.merge(OmegaConf.structured(schema), cfg)
    except OmegaConfBaseException as err:
        raise ConfigError(schema_error_message(err)) from err
    check_ranges(typed)
    return typed


def plugin_models() -> tuple[str, ...]:
    """The plugins' registered world models: those built outside the package."""
    return tuple(m for m in MODELS.names() if not _ours(MODELS[m].build))


def _ours(build: Any) -> bool:
    return getattr(build, "__module__", "").startswith("mbrl_delan.")


def registered(option: str, names: list[str] | None, registry: Registry[Any]) -> None:
    """Each of `names` registered in `registry` (a plugin's once its module is loaded)."""
    for name in names or ():
        if name not in registry:
            raise ConfigError(
                f"{option}: {name!r} is not a registered {registry.family}; choose among: "
                f"{', '.join(registry.names())} (a plugin's needs its module in plugins=[...])"
            )


def known(option: str, names: list[str] | None, choices: tuple[str, ...]) -> None:
    """Each of `names` among `choices` (a suite's cases, a plugin's among them)."""
    if names is not None and any(n not in choices for n in names):
        raise ConfigError(
            f"{option}={names!r} is not valid; use null or a list of: {', '.join(choices)}"
        )
