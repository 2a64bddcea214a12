"""How a training run is assembled from its config (`python -m mbrl_delan.train`'s parts):
the env's parts, the world model, the planner policies (the loop's and the oracle's), the
replay buffer, the `MBRLLoop` and its `Schedule`; `model.init_from`'s mocap fit. Benchmarks,
`runs` and `evaluate` build through here, as the entry point does."""

from __future__ import annotations

import logging
import shutil
from dataclasses import replace
from functools import partial
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf
from torchrl.data import TensorDictReplayBuffer
from torchrl.envs import EnvBase, SerialEnv

from mbrl_delan.accelerate.compile import compile_fit
from mbrl_delan.conf.builders import build_model, build_planner
from mbrl_delan.conf.checks import (
    DTYPES,
    ConfigError,
    build_fit_config,
    check_device,
    check_rollout_steps,
)
from mbrl_delan.conf.schema import AccelConfig
from mbrl_delan.data.buffer import (
    free_device_bytes,
    make_replay_buffer,
    place_buffer,
    transition_nbytes,
)
from mbrl_delan.envs.real import make_real_env
from mbrl_delan.envs.registry import EnvParts, make_env_parts
from mbrl_delan.models.base import WorldModel, model_placement
from mbrl_delan.models.delan import DeLaN
from mbrl_delan.models.delan_config import delan_structure, structure_overrides
from mbrl_delan.objectives.model import model_objective_factory
from mbrl_delan.objectives.mujoco import PlanPhysics, mujoco_objective_factory, mujoco_threads
from mbrl_delan.planners.base import Planner
from mbrl_delan.planners.humanoid_residual import HUMANOID_ILQR, humanoid_ilqr_policy
from mbrl_delan.planners.policy import PlannerPolicy
from mbrl_delan.planners.tracking_residual import TRACKING_ILQR, tracking_ilqr_policy
from mbrl_delan.systems.system import System
from mbrl_delan.tasks.balance import BalanceCost
from mbrl_delan.tasks.base import Task
from mbrl_delan.tasks.humanoid import HumanoidTask
from mbrl_delan.tasks.tracking import MotionTracking
from mbrl_delan.training.inverse_fit import read_fit_run
from mbrl_delan.training.loop import MBRLLoop, Schedule

log = logging.getLogger(__name__)


def _policy(
    planner_cfg: DictConfig, planner: Any, factory: Any, seed: int, device: torch.device
) -> PlannerPolicy:
    return PlannerPolicy(
        planner,
        factory,
        replan_every=planner_cfg.replan_every,
        seed=seed,
        device=device,
        action_dtype=torch.float32,
    )


def _task_options(cfg: DictConfig) -> dict[str, Any] | None:
    """`env.task` (cmu_track: the clip and where to find it) as a plain dict, if the env has it."""
    options = cfg.env.get("task")
    return None if options is None else OmegaConf.to_container(options, resolve=True)


def env_parts(cfg: DictConfig) -> EnvParts:
    """The env's system and task; a bad env setting or a missing clip is a ConfigError."""
    env = cfg.env
    try:
        return make_env_parts(env.name, env.frame_skip, env.episode_len, _task_options(cfg))
    except (ValueError, FileNotFoundError) as err:
        raise ConfigError(f"env={env.name}: {err}") from err


def _planner(cfg: DictConfig, system: System, dtype: torch.dtype) -> Planner:
    """The configured planner; a value it refuses (e.g. temperature <= 0) is a ConfigError."""
    try:
        return build_planner(cfg.planner, system, dtype)
    except ValueError as err:
        raise ConfigError(f"planner={cfg.planner.name}: {err}") from err


def planning_task(cfg: DictConfig, system: System, task: Task) -> Task:
    """What the sampling planners maximise: `task`'s own reward (`env.plan_cost=reward`) or
    a humanoid's balance cost (`balance`, `BalanceCost` over `system`'s MJCF, its target
    speed `env.plan_speed` where set, else the task's)."""
    if cfg.env.plan_cost == "reward":
        return task
    if not isinstance(task, HumanoidTask):
        raise ConfigError(
            f"env.plan_cost={cfg.env.plan_cost} needs a humanoid env (humanoid_stand, "
            f"humanoid_walk, humanoid_stand_exo, humanoid_stand_tendon), got env={cfg.env.name}"
        )
    try:
        return BalanceCost(system.mj_model(), task, speed=cfg.env.plan_speed)
    except ValueError as err:
        raise ConfigError(f"env.plan_cost=balance on env={cfg.env.name}: {err}") from err


def build_oracle(cfg: DictConfig, system: System, task: Task) -> PlannerPolicy:
    """The oracle policy of `budget.oracle_planner`: `same` (the loop's planner on MuJoCo,
    maximising `planning_task`) or `ilqr` (iLQR over `env.oracle_horizon`, null: the
    planner's, on MuJoCo's derivatives, with the tracking residuals on cmu_track and the
    humanoid residuals on humanoid_stand and humanoid_walk)."""
    physics = PlanPhysics(cfg.env.oracle_substeps, cfg.env.oracle_integrator)
    if cfg.budget.oracle_planner == "ilqr":
        return _ilqr_oracle(cfg, system, task, physics)
    log.info("oracle: the loop's planner (%s) on MuJoCo's dynamics", cfg.planner.name)
    oracle_factory = mujoco_objective_factory(
        system, planning_task(cfg, system, task), discount=cfg.planner.discount, physics=physics
    )
    return _policy(
        cfg.planner, _planner(cfg, system, torch.float64), oracle_factory, cfg.seed,
        torch.device("cpu"),
    )  # fmt: skip


def _ilqr_oracle(
    cfg: DictConfig, system: System, task: Task, physics: PlanPhysics
) -> PlannerPolicy:
    nthread = mujoco_threads()
    horizon = cfg.env.oracle_horizon or cfg.planner.horizon
    if isinstance(task, MotionTracking):
        settings = replace(TRACKING_ILQR, horizon=horizon)
        policy = tracking_ilqr_policy(system, task, nthread, settings, physics=physics)
    elif isinstance(task, HumanoidTask):
        settings = replace(HUMANOID_ILQR, horizon=horizon)
        policy = humanoid_ilqr_policy(system, task, nthread, settings, physics=physics)
    else:
        raise ConfigError(
            "budget.oracle_planner=ilqr needs a motion-tracking or humanoid env (cmu_track, "
            f"humanoid_stand, humanoid_walk), got env={cfg.env.name}"
        )
    log.info(
        "oracle: iLQR, horizon %d, %d iterations, on MuJoCo's derivatives (%d threads)",
        settings.horizon, settings.iterations, nthread,
    )  # fmt: skip
    return policy


def build_policy(
    cfg: DictConfig, system: System, task: Task, model: WorldModel, generator: torch.Generator
) -> PlannerPolicy:
    """The loop's policy: its planner over `model`'s imagined returns of `task` (or of the
    balance cost, `planning_task`; compiled, replayed from CUDA graphs or on rollout threads
    as ``accel.*`` says), in the model's device and dtype; `generator` draws the model's
    noise."""
    place = model_placement(model)
    task = planning_task(cfg, system, task)
    factory = model.objective_factory(task, cfg.planner.discount) or model_objective_factory(
        model,
        task,
        particles=cfg.model.particles,
        discount=cfg.planner.discount,
        generator=generator,
        risk=cfg.planner.risk,
        accel=OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(AccelConfig), cfg.accel)),
    )
    planner = _planner(cfg, system, place.dtype)
    return _policy(cfg.planner, planner, factory, cfg.seed, place.device)


def build_world_model(
    cfg: DictConfig, system: System, device: torch.device, dtype: torch.dtype
) -> WorldModel:
    """The loop's world model on its device and dtype, its refits compiled with
    ``accel.compile_fit``."""
    try:
        model = build_model(cfg.model, system).to(device=device, dtype=dtype)
    except ValueError as err:  # a structure the env's system cannot have (yaw_invariant)
        raise ConfigError(f"model={cfg.model.name} on env={cfg.env.name}: {err}") from err
    check_rollout_steps(cfg, model)
    if cfg.accel.compile_fit:
        compile_fit(model)
    return model


def apply_run_settings(cfg: DictConfig) -> None:
    """torch's intra-op threads (`threads`; null: torch's own) and its global seed (`seed`),
    set as the entry points set them before they build anything."""
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)


def build_loop(cfg: DictConfig, run_dir: Path) -> tuple[MBRLLoop, PlannerPolicy]:
    """The MBRL loop and the oracle policy (the same planner over MuJoCo's true dynamics, or
    iLQR on MuJoCo's derivatives with `budget.oracle_planner=ilqr`), built after
    `apply_run_settings`: a loop built from Python runs on `threads` threads from `seed`."""
    apply_run_settings(cfg)
    device, dtype = check_device(cfg.device), DTYPES[cfg.dtype]
    parts = env_parts(cfg)
    system, task = parts.system, parts.task
    env_kw = dict(
        frame_skip=cfg.env.frame_skip,
        episode_len=cfg.env.episode_len,
        task_options=_task_options(cfg),
    )
    env = _collect_env(cfg, env_kw)
    eval_env = make_real_env(cfg.env.name, seed=cfg.seed, **env_kw)
    model = build_world_model(cfg, system, device, dtype)
    optimizer = (  # none for a model that identifies itself
        None
        if model.identifies
        else torch.optim.Adam(
            model.parameters(), lr=cfg.model.lr, weight_decay=cfg.model.weight_decay
        )
    )
    model_gen = torch.Generator(device=device).manual_seed(cfg.seed + 3)
    policy = build_policy(cfg, system, task, model, model_gen)
    oracle = build_oracle(cfg, parts.physics, task)  # plans on the env's own physics
    buffer = _replay_buffer(cfg, run_dir, eval_env, device)
    fit_cfg = build_fit_config(cfg)
    loop = MBRLLoop(
        env,
        eval_env,
        system,
        task.episode_len,
        model,
        optimizer,
        policy,
        buffer,
        fit_cfg,
        seed=cfg.seed,
        error_horizon=cfg.planner.horizon,
        model_generator=model_gen,
        keep_eval_rollouts=cfg.video_episodes if cfg.video else 0,
        fidelity_task=task if isinstance(task, HumanoidTask) else None,
        physics=parts.physics,
    )
    return loop, oracle


def _collect_env(cfg: DictConfig, env_kw: dict[str, Any]) -> EnvBase:
    """The env the loop collects with: one real env, or `budget.collect_envs` of them as
    TorchRL's `SerialEnv` (each round then collects one episode per env)."""
    n = cfg.budget.collect_envs
    if n == 1:
        return make_real_env(cfg.env.name, seed=cfg.seed, **env_kw)
    env = SerialEnv(n, partial(make_real_env, cfg.env.name, **env_kw))
    env.set_seed(cfg.seed)
    return env


MEMMAP_DIR = "buffer"  # <run dir>/buffer: the memmap of `buffer.memmap=true`


def _replay_buffer(
    cfg: DictConfig, run_dir: Path, env: EnvBase, model_device: torch.device
) -> TensorDictReplayBuffer:
    """The replay buffer: a memmap in `<run dir>/buffer` (`buffer.memmap`), else in memory on
    `buffer.device` (auto: the model's device when the full buffer fits, see `place_buffer`)."""
    if cfg.buffer.memmap:
        folder = run_dir / MEMMAP_DIR
        if folder.exists():  # an earlier process's files; a resume reloads from the checkpoint
            log.info("replay buffer: clearing the earlier memmap in %s", folder)
            shutil.rmtree(folder)
        log.info("replay buffer: memmap in %s", folder)
        return make_replay_buffer(cfg.buffer.capacity, memmap_dir=str(folder))
    place = place_buffer(
        str(cfg.buffer.device),
        model_device,
        cfg.buffer.capacity * transition_nbytes(env),
        free_device_bytes(model_device),
        cfg.buffer.device_fraction,
    )
    log.info("replay buffer: on %s (%s)", place.device, place.reason)
    return make_replay_buffer(cfg.buffer.capacity, device=place.device)


# the fit's model keys that make up M, V and the friction (`Structure.MECHANICS`)
FIT_STRUCTURE_KEYS = (
    "hidden", "layers", "activation", "diag_shift", "dissipation", "coulomb",
    "still_first_order", "tree_sparse", "armature",
)  # fmt: skip


def with_fit_structure(cfg: DictConfig) -> DictConfig:
    """`model.init_from`: the loop's DeLaN takes the mocap fit's structure (the keys above,
    its ``translation_invariant``, no ``yaw_invariant``), so that one key starts the loop
    from the fit. Returns the config with those model keys set; logs the ones it changed."""
    fit_cfg, _ = _read_mocap_fit(cfg.model)
    wanted = {key: fit_cfg.model[key] for key in FIT_STRUCTURE_KEYS if key in fit_cfg.model}
    wanted |= {
        "translation_invariant": bool(fit_cfg.get("translation_invariant", False)),
        "yaw_invariant": False,
    }
    changed = {key: value for key, value in wanted.items() if cfg.model[key] != value}
    if changed:
        cfg = cfg.copy()
        for key, value in changed.items():
            cfg.model[key] = value
        log.info(
            "model.init_from=%r: the DeLaN takes that fit's structure: %s",
            cfg.model.init_from,
            " ".join(f"model.{key}={value}" for key, value in changed.items()),
        )
    return cfg


def _read_mocap_fit(model_cfg: DictConfig) -> tuple[DictConfig, dict[str, torch.Tensor]]:
    """The config and model state of the DeLaN fit `model.init_from` names; a `ConfigError`
    when the loop's model is not a DeLaN or the folder holds no DeLaN fit."""
    where = f"model.init_from={model_cfg.init_from!r}"
    if model_cfg.name != "delan":
        raise ConfigError(f"{where} is for model=delan, not model={model_cfg.name}")
    try:
        fit_cfg, state = read_fit_run(model_cfg.init_from)
    except (FileNotFoundError, ValueError) as err:
        raise ConfigError(f"{where}: {err}") from err
    if fit_cfg.model.name != "delan":
        raise ConfigError(f"{where}: that fit is model={fit_cfg.model.name}, not a DeLaN")
    return fit_cfg, state


def start_mechanics(model_cfg: DictConfig, model: DeLaN, system: System) -> None:
    """`model.init_from`: M, V and the friction of a DeLaN fitted on motion capture."""
    fit_cfg, state = _read_mocap_fit(model_cfg)
    where = f"model.init_from={model_cfg.init_from!r}"
    ours = delan_structure(model_cfg, system)
    theirs = delan_structure(  # the mocap fit's DeLaN sees the root's heading
        fit_cfg.model,
        system,
        translation_invariant=fit_cfg.get("translation_invariant", False),
        yaw_invariant=False,
    )
    differ = ours.differences(theirs)
    if differ:
        add = " ".join(structure_overrides(theirs, differ))
        raise ConfigError(f"{where}: that DeLaN was fitted with another structure; add {add}")
    delan_state = {k.removeprefix("delan."): v for k, v in state.items() if k.startswith("delan.")}
    try:
        model.load_mechanics(delan_state)
    except ValueError as err:  # another system (env) than the fit's humanoid
        raise ConfigError(f"{where}: {err}") from err
    log.info("started M, V and the friction from the mocap fit in %s", model_cfg.init_from)


def schedule_of(cfg: DictConfig) -> Schedule:
    """The run's `Schedule` from ``cfg.budget``."""
    b = cfg.budget
    return Schedule(
        oracle_episodes=b.oracle_episodes,
        random_episodes=b.random_episodes,
        iterations=b.iterations,
        eval_every=b.eval_every,
        eval_episodes=b.eval_episodes,
        final_eval_episodes=b.final_eval_episodes,
        env_steps=b.env_steps,
        paired=b.paired,
    )
