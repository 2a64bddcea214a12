"""The package's envs (which MJCF system, which task, their defaults) and `make_env_parts`.

Each env is an entry of `mbrl_delan.registry.ENVS`, added with `register_env`; a user's own
env registers the same way from their module (docs/architecture.md, "How to add an env").
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, fields
from typing import Any, TypeVar

import torch

from mbrl_delan.registry import ENVS, EnvSpec, TaskFactory, register_env
from mbrl_delan.systems.external import (
    humanoid_cmu_xml,
    humanoid_v5_exo_xml,
    humanoid_v5_tendon_xml,
    humanoid_v5_xml,
)
from mbrl_delan.systems.system import System, load_system
from mbrl_delan.tasks import AcrobotSwingup, ArmReach, CartpoleSwingup, PendulumSwingup
from mbrl_delan.tasks.base import Task
from mbrl_delan.tasks.humanoid import HUMANOID_V5_BODY, HumanoidTask
from mbrl_delan.tasks.tracking import (
    MotionTracking,
    TrackingScales,
    TrackingWeights,
    ground_reference,
)

TaskOptions = Mapping[str, Any]
TermSettings = TypeVar("TermSettings", TrackingWeights, TrackingScales)
# cmu_track's task options: the clip to follow and where to find its AMC and ASF files
# (`data.mocap.find_clip`: the folders first, relative to the cwd, then the download cache)
CMU_TRACK_OPTIONS: dict[str, Any] = {
    "clip": "02_01",  # CMU subject 2, trial 1: a walk (2.9 s)
    "folders": ("../shared/data/cmu_mocap", "data/cmu_mocap"),
    "cache_dir": None,
    "download": True,
    "ground": True,
    "weights": None,  # {pose, velocity, end_effector, root}; None: TrackingWeights' defaults
    "scales": None,  # k of each term exp(-k error^2); None: TrackingScales' defaults
}


@dataclass
class EnvParts:
    """The system the world models are given, the task (reward, initial states) and the
    system the env simulates (`physics`: the same unless the env registered its own)."""

    system: System
    task: Task
    physics: System | None = None

    def __post_init__(self) -> None:
        if self.physics is None:
            self.physics = self.system


def _humanoid_v5_task(
    speed: float | None, name: str
) -> Callable[[System, int | None, TaskOptions], Task]:
    """Stand (speed None) or walk on gymnasium's Humanoid-v5 (controls in [-0.4, 0.4])."""

    def make(system: System, episode_len: int | None, options: TaskOptions) -> Task:
        extra = {} if episode_len is None else {"episode_len": episode_len}
        ctrl_max = float(system.ctrl_high.abs().max())
        return HumanoidTask(
            system.mj_model(), HUMANOID_V5_BODY, speed, ctrl_max=ctrl_max, name=name, **extra
        )

    return make


def _cmu_track_task(system: System, episode_len: int | None, options: TaskOptions) -> Task:
    """Follow a CMU clip retargeted onto the CMU humanoid at the control rate."""
    from mbrl_delan.data.mocap import find_clip, retarget_files  # heavy: only for this env

    clip_name = options["clip"]
    if not isinstance(clip_name, str):
        raise ValueError(
            f"clip={clip_name!r} is not a clip name; quote it, as in clip='131_03' (Hydra and "
            "YAML read an unquoted 131_03 as the number 13103)"
        )
    if not isinstance(options["ground"], bool):
        raise ValueError(f"ground={options['ground']!r} is not valid; it must be true or false")
    weights = term_settings(TrackingWeights, options["weights"], "weights")
    scales = term_settings(TrackingScales, options["scales"], "scales")
    files = find_clip(
        clip_name,
        folders=list(options["folders"]),
        cache_dir=options["cache_dir"],
        download=bool(options["download"]),
    )
    clip = retarget_files(files.amc, files.asf, timestep=system.control_dt)
    ref_q = torch.cat([clip.q, clip.next_q[-1:]])  # (T+1, nq)
    ref_qd = torch.cat([clip.qd, clip.next_qd[-1:]])  # (T+1, nv)
    if options["ground"]:
        ref_q, ref_qd = ground_reference(system.mj_model(), ref_q, ref_qd, system.control_dt)
    return MotionTracking(
        system.mj_model(),
        system.layout,
        ref_q,
        ref_qd,
        weights=weights,
        scales=scales,
        episode_len=episode_len,
        name="cmu_track",
    )


def term_settings(
    cls: type[TermSettings], given: Mapping[str, Any] | None, option: str
) -> TermSettings:
    """`cls` (`TrackingWeights` or `TrackingScales`) with the given terms replaced (None: its
    defaults); a term that is not one of its fields, or a value that is not a number, is
    refused with the option's name."""
    if given is None:
        return cls()
    if not isinstance(given, Mapping):
        raise ValueError(f"{option}={given!r} is not valid; give a mapping of term -> number")
    terms = {f.name for f in fields(cls)}
    unknown = sorted(map(str, set(given) - terms))
    if unknown:
        raise ValueError(
            f"{option}: no term {', '.join(unknown)} (terms: {', '.join(sorted(terms))})"
        )
    bad = {k: v for k, v in given.items() if isinstance(v, bool) or not isinstance(v, int | float)}
    if bad:
        raise ValueError(f"{option}: {bad} are not numbers")
    return cls(**{k: float(v) for k, v in given.items()})


def _episode_len_task(cls: Callable[..., Task]) -> TaskFactory:
    """The task factory of a task class whose only option is its episode length."""

    def make(system: System, episode_len: int | None, options: TaskOptions) -> Task:
        return cls() if episode_len is None else cls(episode_len=episode_len)

    return make


# the package's envs; control step = frame_skip x the MJCF's timestep
register_env("pendulum", "pendulum", 2)(_episode_len_task(PendulumSwingup))  # 0.05 s
register_env("cartpole", "cartpole", 2)(_episode_len_task(CartpoleSwingup))  # 0.04 s
register_env("acrobot", "acrobot", 2)(_episode_len_task(AcrobotSwingup))  # 0.05 s
register_env("arm_reach", "arm2", 2)(_episode_len_task(ArmReach))  # 0.05 s
# Humanoid-v5 (contacts on): 5 x 0.003 s = 0.015 s per control step
register_env("humanoid_stand", humanoid_v5_xml, 5)(_humanoid_v5_task(None, "humanoid_stand"))
register_env("humanoid_walk", humanoid_v5_xml, 5)(_humanoid_v5_task(1.0, "humanoid_walk"))
# Humanoid-v5 in an exoskeleton (springs at the hips and knees, joint friction: EXOSKELETON):
# the env simulates it, the world models are given Humanoid-v5's own MJCF
register_env("humanoid_stand_exo", humanoid_v5_xml, 5, physics=humanoid_v5_exo_xml)(
    _humanoid_v5_task(None, "humanoid_stand_exo")
)
# Humanoid-v5 with elastic bands over two joints each (hip and knee, abdomen and hip: BANDS):
# the env simulates them, the world models are given Humanoid-v5's own MJCF
register_env("humanoid_stand_tendon", humanoid_v5_xml, 5, physics=humanoid_v5_tendon_xml)(
    _humanoid_v5_task(None, "humanoid_stand_tendon")
)
# dm_control's CMU humanoid (contacts on): 15 x 0.002 s = 0.03 s per control step
register_env("cmu_track", humanoid_cmu_xml, 15, CMU_TRACK_OPTIONS)(_cmu_track_task)


def _task_options(name: str, options: TaskOptions | None) -> dict[str, Any]:
    """The env's task options with the given ones applied; unknown keys are refused."""
    accepted = dict(ENVS[name].build.options or {})
    given = dict(options or {})
    unknown = sorted(set(given) - set(accepted))
    if unknown:
        takes = ", ".join(accepted) if accepted else "none"
        raise ValueError(
            f"env {name!r} takes no task option {', '.join(unknown)} (it takes: {takes})"
        )
    return {**accepted, **given}


def make_env_parts(
    name: str,
    frame_skip: int | None = None,
    episode_len: int | None = None,
    task_options: TaskOptions | None = None,
) -> EnvParts:
    """System and task of env `name`; None keeps the env's default frame_skip / episode_len.

    `task_options` override the env's task options (only cmu_track has some:
    `CMU_TRACK_OPTIONS`).
    """
    if name not in ENVS:
        raise ValueError(f"unknown env name {name!r}; valid choices: {', '.join(ENVS.names())}")
    if episode_len is not None and episode_len < 1:
        raise ValueError(f"episode_len must be >= 1, got {episode_len}")
    spec: EnvSpec = ENVS[name].build
    options = _task_options(name, task_options)
    skip = spec.frame_skip if frame_skip is None else frame_skip
    asset = spec.asset() if callable(spec.asset) else spec.asset
    system = load_system(asset, frame_skip=skip)
    physics = None
    if spec.physics is not None:
        path = spec.physics() if callable(spec.physics) else spec.physics
        physics = load_system(path, frame_skip=skip, name=f"{system.name} ({name})")
    return EnvParts(system, spec.make_task(system, episode_len, options), physics)
