"""mbrl_delan: model-based RL on TorchRL with Deep Lagrangian Networks as the world model.

Importing the package registers a gymnasium id for each built-in env (`gym_id`, e.g.
``gym.make("mbrl_delan/Pendulum-v0")``); the envs load only when made. A plugin's envs get
theirs from `mbrl_delan.envs.register_envs` (`make_real_env` calls it).
"""

import gymnasium

__version__ = "0.1.0"

# the env registry's built-in envs (`mbrl_delan.registry.ENVS`; a test checks they agree),
# named here so that the import registers their ids without loading them
BUILTIN_ENVS = (
    "pendulum", "cartpole", "acrobot", "arm_reach", "humanoid_stand", "humanoid_walk",
    "cmu_track",
)  # fmt: skip
ENTRY_POINT = "mbrl_delan.envs.real:MujocoTaskEnv"


def gym_id(name: str) -> str:
    """The gymnasium id of a registered env: ``mbrl_delan/<Name>-v0`` (arm_reach: ArmReach)."""
    return "mbrl_delan/" + "".join(part.capitalize() for part in name.split("_")) + "-v0"


def register_gym_id(name: str) -> None:
    """Register env `name`'s gymnasium id, made by `MujocoTaskEnv` (idempotent)."""
    if gym_id(name) not in gymnasium.registry:
        gymnasium.register(id=gym_id(name), entry_point=ENTRY_POINT, kwargs={"env_name": name})


for _name in BUILTIN_ENVS:
    register_gym_id(_name)
