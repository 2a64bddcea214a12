"""Environments: the real MuJoCo env (gymnasium + TorchRL) and the package's registered envs.

Importing this package registers a gymnasium id for every registered env (`gym_id`, e.g.
mbrl_delan/Pendulum-v0); `make_real_env` registers those of envs added later.
"""

from mbrl_delan.envs.model_env import ModelEnv
from mbrl_delan.envs.modules import ReturnToGo, TaskReward, Transition, world_model_wrapper
from mbrl_delan.envs.real import (
    MujocoTaskEnv,
    env_parts_of,
    gym_id,
    make_real_env,
    register_envs,
)
from mbrl_delan.envs.registry import EnvParts, make_env_parts

register_envs()

__all__ = [
    "EnvParts",
    "ModelEnv",
    "MujocoTaskEnv",
    "ReturnToGo",
    "TaskReward",
    "Transition",
    "env_parts_of",
    "gym_id",
    "make_env_parts",
    "make_real_env",
    "register_envs",
    "world_model_wrapper",
]
