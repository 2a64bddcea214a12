"""Named environments: which MJCF system, which task, and their default settings."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from mbrl_delan.systems.external import humanoid_v5_xml
from mbrl_delan.systems.system import System, load_system
from mbrl_delan.tasks import AcrobotSwingup, ArmReach, CartpoleSwingup, PendulumSwingup
from mbrl_delan.tasks.base import Task
from mbrl_delan.tasks.humanoid import HUMANOID_V5_BODY, HumanoidTask

ENV_NAMES = ("pendulum", "cartpole", "acrobot", "arm_reach", "humanoid_stand", "humanoid_walk")


@dataclass
class EnvParts:
    """The system (dynamics) and task (reward, initial states) of one environment."""

    system: System
    task: Task


@dataclass(frozen=True)
class _EnvDefaults:
    asset: str | Callable[[], Path]  # MJCF stem under systems/assets, or where to find the file
    frame_skip: int  # MuJoCo steps per control step (0.025 s each; cartpole 0.02 s)
    make_task: Callable[[System, int | None], Task]  # (system, episode_len or None) -> task


def _task_factory(cls: Callable[..., Task]) -> Callable[[System, int | None], Task]:
    def make(system: System, episode_len: int | None) -> Task:
        return cls() if episode_len is None else cls(episode_len=episode_len)

    return make


def _humanoid_v5_task(speed: float | None, name: str) -> Callable[[System, int | None], Task]:
    """Stand (speed None) or walk on gymnasium's Humanoid-v5 (controls in [-0.4, 0.4])."""

    def make(system: System, episode_len: int | None) -> Task:
        extra = {} if episode_len is None else {"episode_len": episode_len}
        ctrl_max = float(system.ctrl_high.abs().max())
        return HumanoidTask(
            system.mj_model(), HUMANOID_V5_BODY, speed, ctrl_max=ctrl_max, name=name, **extra
        )

    return make


_DEFAULTS: dict[str, _EnvDefaults] = {
    "pendulum": _EnvDefaults("pendulum", 2, _task_factory(PendulumSwingup)),  # dt 0.05 s
    "cartpole": _EnvDefaults("cartpole", 2, _task_factory(CartpoleSwingup)),  # dt 0.04 s
    "acrobot": _EnvDefaults("acrobot", 2, _task_factory(AcrobotSwingup)),  # dt 0.05 s
    "arm_reach": _EnvDefaults("arm2", 2, _task_factory(ArmReach)),  # dt 0.05 s
    # Humanoid-v5 (contacts on): 5 x 0.003 s = 0.015 s per control step
    "humanoid_stand": _EnvDefaults(humanoid_v5_xml, 5, _humanoid_v5_task(None, "humanoid_stand")),
    "humanoid_walk": _EnvDefaults(humanoid_v5_xml, 5, _humanoid_v5_task(1.0, "humanoid_walk")),
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
    asset = defaults.asset if isinstance(defaults.asset, str) else defaults.asset()
    system = load_system(asset, frame_skip=skip)
    return EnvParts(system=system, task=defaults.make_task(system, episode_len))
