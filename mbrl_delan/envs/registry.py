"""Named environments: which MJCF system, which task, and their default settings."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from mbrl_delan.systems.system import System, load_system
from mbrl_delan.tasks import AcrobotSwingup, ArmReach, CartpoleSwingup, PendulumSwingup
from mbrl_delan.tasks.base import Task

ENV_NAMES = ("pendulum", "cartpole", "acrobot", "arm_reach")


@dataclass
class EnvParts:
    """The system (dynamics) and task (reward, initial states) of one environment."""

    system: System
    task: Task


@dataclass(frozen=True)
class _EnvDefaults:
    asset: str  # MJCF stem under systems/assets
    frame_skip: int  # MuJoCo steps per control step (0.025 s each; cartpole 0.02 s)
    make_task: Callable[[int | None], Task]  # episode_len (None: task default) -> task


def _task_factory(cls: Callable[..., Task]) -> Callable[[int | None], Task]:
    def make(episode_len: int | None) -> Task:
        return cls() if episode_len is None else cls(episode_len=episode_len)

    return make


_DEFAULTS: dict[str, _EnvDefaults] = {
    "pendulum": _EnvDefaults("pendulum", 2, _task_factory(PendulumSwingup)),  # dt 0.05 s
    "cartpole": _EnvDefaults("cartpole", 2, _task_factory(CartpoleSwingup)),  # dt 0.04 s
    "acrobot": _EnvDefaults("acrobot", 2, _task_factory(AcrobotSwingup)),  # dt 0.05 s
    "arm_reach": _EnvDefaults("arm2", 2, _task_factory(ArmReach)),  # dt 0.05 s
}


def make_env_parts(
    name: str, frame_skip: int | None = None, episode_len: int | None = None
) -> EnvParts:
    """System and task of env `name`; None keeps the env's default frame_skip / episode_len."""
    if name not in _DEFAULTS:
        raise ValueError(f"unknown env name {name!r}; valid choices: {', '.join(ENV_NAMES)}")
    if episode_len is not None and episode_len < 1:
        raise ValueError(f"episode_len must be >= 1, got {episode_len}")
    defaults = _DEFAULTS[name]
    skip = defaults.frame_skip if frame_skip is None else frame_skip
    system = load_system(defaults.asset, frame_skip=skip)
    return EnvParts(system=system, task=defaults.make_task(episode_len))
