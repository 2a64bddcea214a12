"""Typed schemas of the training config, one dataclass per config group.

The YAML files under ``mbrl_delan/configs/train`` hold the values (with a comment each); these
dataclasses hold the types and the valid ranges. Each is stored in Hydra's ConfigStore at the
top level (``base_train``, ``base_env``, ``base_delan``, ``base_mppi``, ...: not group options,
so ``--help`` lists only the real choices) and each YAML file extends its schema in its
defaults list (``- /base_env@_here_``), so a value of the wrong type
(``budget.iterations=1.5``) or a key that does not exist fails when Hydra composes the config,
naming the key. Ranges and the rules that tie keys together are checked by
`mbrl_delan.conf.checks.validate_train_config`, which reads the ``low`` / ``high`` / ``choices``
metadata of these fields (`mbrl_delan.rules.field_rule`).

A user's model or planner brings its own schema (`mbrl_delan.registry.register_model(name,
schema=...)`), an env YAML of their own extends ``/base_env@_here_``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING

from mbrl_delan.models.base import ModelConfig as ModelConfig  # a user's schema extends these
from mbrl_delan.models.integrators import INTEGRATORS
from mbrl_delan.objectives.model import RolloutSettings
from mbrl_delan.objectives.mujoco import INTEGRATORS as ORACLE_INTEGRATORS
from mbrl_delan.planners.base import PlannerConfig as PlannerConfig
from mbrl_delan.registry import MODELS, PLANNERS
from mbrl_delan.rules import rule
from mbrl_delan.tasks.balance import PLAN_COSTS
from mbrl_delan.training.fit import FitConfig
from mbrl_delan.training.recorder import LOGGERS, WANDB_MODES


@dataclass
class EnvConfig:
    """``env``: which registered env, its episode and the defaults it gives other groups."""

    name: str = MISSING
    frame_skip: int | None = rule(None, low=1)  # null: the env's registered frame_skip
    episode_len: int | None = rule(None, low=1)  # null: the task's default
    horizon: int = rule(low=1)  # the planners' horizon (planner.horizon)
    random_episodes: int = rule(1, low=1)
    iterations: int = rule(low=1)
    env_steps: int | None = rule(None, low=1)  # the run's env-step budget (null: rounds only)
    eval_every: int = rule(1, low=1)
    eval_episodes: int = rule(2, low=0)
    final_eval_episodes: int = rule(5, low=0)
    paired_eval: bool = False  # the final evaluation paired with the oracle's (budget.paired)
    model_integrator: str = rule("euler", choices=INTEGRATORS)
    model_substeps: int = rule(1, low=1)
    model_residual: bool = False
    model_contacts: bool = False
    model_inertia_scaling: bool = False
    model_known_root: bool = False
    plan_cost: str = rule("reward", choices=PLAN_COSTS)  # planners' objective (balance: humanoids)
    plan_speed: float | None = rule(None, low=0)  # balance: target speed, m/s (null: the task's)
    oracle_planner: str = rule("same", choices=("same", "ilqr"))
    oracle_substeps: int | None = rule(None, low=1)  # null: frame_skip
    oracle_integrator: str | None = rule(None, choices=tuple(ORACLE_INTEGRATORS))  # null: MJCF's
    oracle_horizon: int | None = rule(None, low=1)  # the iLQR oracle's (null: the planner's)
    task: dict[str, Any] = field(default_factory=dict)  # task options (cmu_track: the clip)


@dataclass
class LoggerConfig:
    """``logger``: none, wandb (offline unless the user logs in), TorchRL's csv or tensorboard."""

    backend: str = rule(choices=LOGGERS)
    project: str = "mbrl_delan"
    group: str | None = None
    name: str | None = None  # wandb run name (None: wandb's own)
    tags: list[str] = field(default_factory=list)
    entity: str | None = None  # wandb team or user (None: the logged-in user's default)
    mode: str | None = rule(None, choices=WANDB_MODES)  # None: WANDB_MODE, else offline


@dataclass
class BudgetConfig:
    """``budget``: episodes and rounds of a run."""

    random_episodes: int = rule(low=1)  # the first fit needs data
    iterations: int = rule(low=1)
    env_steps: int | None = rule(None, low=1)
    eval_every: int = rule(low=1)
    eval_episodes: int = rule(low=0)
    final_eval_episodes: int = rule(low=0)
    oracle_episodes: int = rule(low=0)
    oracle_planner: str = rule(choices=("same", "ilqr"))
    collect_envs: int = rule(1, low=1)  # episodes collected at once, one per env
    paired: bool = False  # the final evaluation and the oracle's share starts and planner seeds
    oracle_from: str | None = None  # a run dir whose oracle and zero-torque episodes this run takes


@dataclass
class BufferConfig:
    """``buffer``: the replay buffer."""

    capacity: int = rule(low=1)
    memmap: bool = MISSING
    device: str = "auto"
    device_fraction: float = rule(0.5, low=0, above=True, high=1)


@dataclass
class AccelConfig(RolloutSettings):
    """``accel``: how the loop's planning rollouts (`RolloutSettings`, which the model
    objective takes: `objectives.model.ModelObjectiveFactory`) and refits run fast, for any
    world model (`mbrl_delan.accelerate`)."""

    compile_fit: bool = False


ACCEL_KEYS = tuple(f.name for f in fields(AccelConfig))


@dataclass
class TrainConfig:
    """The whole config of ``python -m mbrl_delan.train``."""

    env: EnvConfig = MISSING
    model: Any = MISSING  # typed by the model's own schema
    planner: Any = MISSING  # typed by the planner's own schema
    logger: LoggerConfig = MISSING
    budget: BudgetConfig = MISSING
    buffer: BufferConfig = MISSING
    fit: FitConfig = MISSING
    accel: AccelConfig = field(default_factory=AccelConfig)
    seed: int = rule(0, low=0)
    device: str = "cpu"
    dtype: str = rule("float32", choices=("float32", "float64"))
    threads: int | None = rule(None, low=1)
    resume: str | None = None
    plugins: list[str] = field(default_factory=list)  # modules that register envs, models...
    video: bool = False
    video_width: int = rule(320, low=2)
    video_height: int = rule(240, low=2)
    video_episodes: int = rule(1, low=1)
    video_every_eval: bool = False
    video_backend: str | None = rule(None, choices=("egl", "osmesa", "glfw"))


def store_schemas(store: ConfigStore) -> None:
    """Put the schemas in Hydra's ConfigStore, where the YAML files' defaults lists find them:
    the run's groups and each registered model's and planner's (``base_<name>``)."""
    store.store(name="base_train", node=TrainConfig)
    store.store(name="base_env", node=EnvConfig)
    for registry in (MODELS, PLANNERS):
        for name in registry.names():
            if (schema := registry[name].schema) is not None:
                store.store(name=f"base_{name}", node=schema)


store_schemas(ConfigStore.instance())
