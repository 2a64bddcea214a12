"""Environments: the real MuJoCo env (gymnasium + TorchRL) and the env registry.

Importing this package registers the gymnasium ids in `ENV_IDS` (e.g. mbrl_delan/Pendulum-v0).
"""

from mbrl_delan.envs.model_env import ModelEnv, model_objective_factory
from mbrl_delan.envs.real import (
    ENV_IDS,
    MujocoTaskEnv,
    env_parts_of,
    make_real_env,
    register_envs,
)
from mbrl_delan.envs.registry import ENV_NAMES, EnvParts, make_env_parts

register_envs()

__all__ = [
    "ENV_IDS",
    "ENV_NAMES",
    "EnvParts",
    "ModelEnv",
    "MujocoTaskEnv",
    "env_parts_of",
    "make_env_parts",
    "make_real_env",
    "model_objective_factory",
    "register_envs",
]
