"""`python -m mbrl_delan.train`: model-based RL with a learned world model and a sampling planner.

Builds the parts from the Hydra config, runs the loop of `training/loop.py`, checkpoints
every round (atomically) and writes `metrics.jsonl`, `summary.json` and plots in the run dir.
`resume=<run dir>` continues a stopped run from its last checkpoint with its saved config.
"""

from __future__ import annotations

import json
import logging
import shutil
from dataclasses import replace
from functools import partial
from pathlib import Path
from typing import Any

import hydra
import torch
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDictBase
from torchrl.data import TensorDictReplayBuffer
from torchrl.envs import EnvBase, SerialEnv
from tqdm import tqdm

from mbrl_delan.accelerate.compile import compile_fit
from mbrl_delan.config import (
    DTYPES,
    ConfigError,
    build_fit_config,
    build_model,
    build_planner,
    check_device,
    delan_structure,
    exit_on_config_errors,
    structure_overrides,
    validate_train_config,
)
from mbrl_delan.data.buffer import (
    NonFiniteDataError,
    free_device_bytes,
    make_replay_buffer,
    place_buffer,
    transition_nbytes,
)
from mbrl_delan.envs.real import make_real_env
from mbrl_delan.envs.registry import EnvParts, make_env_parts
from mbrl_delan.models.base import WorldModel, model_placement
from mbrl_delan.models.delan import DeLaN
from mbrl_delan.objectives.model import model_objective_factory
from mbrl_delan.objectives.mujoco import PlanPhysics, available_cpus, mujoco_objective_factory
from mbrl_delan.planners.base import SamplingPlanner
from mbrl_delan.planners.humanoid_residual import HUMANOID_ILQR, humanoid_ilqr_policy
from mbrl_delan.planners.policy import PlannerPolicy
from mbrl_delan.planners.tracking_residual import TRACKING_ILQR, tracking_ilqr_policy
from mbrl_delan.sweep import exit_or_raise, marks_crash, resumed_config, with_sweep_group
from mbrl_delan.systems.external import MissingPackageError
from mbrl_delan.systems.system import System
from mbrl_delan.tasks.base import Task
from mbrl_delan.tasks.humanoid import HumanoidTask
from mbrl_delan.tasks.tracking import MotionTracking
from mbrl_delan.training.checkpoint import (
    CHECKPOINT_FILE,
    CheckpointError,
    atomic_write,
    load_checkpoint,
    prev_path,
    remove_stale_temps,
    rng_state,
    save_checkpoint,
    set_rng_state,
)
from mbrl_delan.training.fit import TrainingDivergedError
from mbrl_delan.training.loop import LoopHooks, MBRLLoop, Schedule
from mbrl_delan.training.plots import plot_run
from mbrl_delan.training.recorder import (
    METRICS_FILE,
    RUN_CONFIG,
    SUMMARY_FILE,
    Recorder,
    WandbOptions,
    read_metrics,
    resume_metrics,
)
from mbrl_delan.training.video import (
    RENDER_ERRORS,
    VideoBackendError,
    VideoRecorder,
    check_backend,
    resolve_backend,
    rollout_states,
    root_travels,
    step_reward_overlays,
)

log = logging.getLogger("mbrl_delan.train")


OmegaConf.register_new_resolver(
    "run_dir_or", lambda resume, default: resume or default, replace=True
)


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


def _planner(cfg: DictConfig, system: System, dtype: torch.dtype) -> SamplingPlanner:
    """The configured planner; a value it refuses (e.g. temperature <= 0) is a ConfigError."""
    try:
        return build_planner(cfg.planner, system, dtype)
    except ValueError as err:
        raise ConfigError(f"planner={cfg.planner.name}: {err}") from err


def build_oracle(cfg: DictConfig, system: System, task: Task) -> PlannerPolicy:
    """The oracle policy of `budget.oracle_planner`: `same` (the loop's planner on MuJoCo) or
    `ilqr` (iLQR over `env.oracle_horizon`, null: the planner's, on MuJoCo's derivatives, with
    the tracking residuals on cmu_track and the humanoid residuals on humanoid_stand and
    humanoid_walk)."""
    physics = PlanPhysics(cfg.env.oracle_substeps, cfg.env.oracle_integrator)
    if cfg.budget.oracle_planner == "ilqr":
        return _ilqr_oracle(cfg, system, task, physics)
    log.info("oracle: the loop's planner (%s) on MuJoCo's dynamics", cfg.planner.name)
    oracle_factory = mujoco_objective_factory(
        system, task, discount=cfg.planner.discount, physics=physics
    )
    return _policy(
        cfg.planner, _planner(cfg, system, torch.float64), oracle_factory, cfg.seed,
        torch.device("cpu"),
    )  # fmt: skip


def _ilqr_oracle(
    cfg: DictConfig, system: System, task: Task, physics: PlanPhysics
) -> PlannerPolicy:
    nthread = min(available_cpus(), 8)
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
    """The loop's policy: its planner over `model`'s imagined returns of `task` (compiled,
    replayed from CUDA graphs or on rollout threads as ``model.*`` says), in the model's
    device and dtype; `generator` draws the model's noise."""
    place = model_placement(model)
    factory = model.objective_factory(task, cfg.planner.discount) or model_objective_factory(
        model,
        task,
        particles=cfg.model.particles,
        discount=cfg.planner.discount,
        generator=generator,
        risk=cfg.planner.risk,
        compile=cfg.model.get("compile", False),  # models without the key: never compiled
        cuda_graph=cfg.model.get("cuda_graph", False),
        rollout_threads=cfg.model.get("rollout_threads"),
    )
    planner = _planner(cfg, system, place.dtype)
    return _policy(cfg.planner, planner, factory, cfg.seed, place.device)


def build_world_model(
    cfg: DictConfig, system: System, device: torch.device, dtype: torch.dtype
) -> WorldModel:
    """The loop's world model on its device and dtype, its refits compiled with
    ``model.compile_fit``."""
    try:
        model = build_model(cfg.model, system).to(device=device, dtype=dtype)
    except ValueError as err:  # a structure the env's system cannot have (yaw_invariant)
        raise ConfigError(f"model={cfg.model.name} on env={cfg.env.name}: {err}") from err
    if cfg.model.get("compile_fit", False):
        compile_fit(model)
    return model


def build_loop(cfg: DictConfig, run_dir: Path) -> tuple[MBRLLoop, PlannerPolicy]:
    """The MBRL loop and the oracle policy (the same planner over MuJoCo's true dynamics, or
    iLQR on MuJoCo's derivatives with `budget.oracle_planner=ilqr`)."""
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
    oracle = build_oracle(cfg, system, task)
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


def _save(run_dir: Path, loop: MBRLLoop) -> None:
    state = {
        "loop": loop.state_dict(),
        "rng": rng_state(),
        "oracle_returns": loop.oracle_returns,
        "warmup_done": loop.warmup_done,
    }
    save_checkpoint(run_dir / CHECKPOINT_FILE, state)


VIDEO_DIR = "videos"


def _check_video(cfg: DictConfig) -> None:
    """With `video=true`: check the video keys and render a test frame, before any training."""
    if not cfg.video:
        return
    for key in ("video_width", "video_height"):
        if cfg[key] % 2:
            raise ConfigError(f"{key}={cfg[key]!r} is not valid; it must be an even integer >= 2")
    try:
        backend = check_backend(cfg.video_backend)
    except VideoBackendError as err:
        raise ConfigError(f"video=true: {err}") from err
    log.info("videos: MuJoCo renders with the %r OpenGL backend", backend)


def _record_episode(video: VideoRecorder, path: Path, rollout: TensorDictBase, task: Task) -> Path:
    """One episode's MP4; a tracking task's shows its reference pose as a translucent ghost
    in each frame."""
    q, qd = rollout_states(rollout)
    overlays = step_reward_overlays(rollout)
    ghost = task.reference_poses(q.shape[0]) if isinstance(task, MotionTracking) else None
    return video.record(path, q, qd, overlays, ghost)


def _write_videos(cfg: DictConfig, run_dir: Path, loop: MBRLLoop, recorder: Recorder) -> None:
    """Render the kept episodes of this round's evaluation to ``<run dir>/videos`` and wandb,
    and at the final one the oracle's (``oracle_ep<j>.mp4``); a tracking task's reference
    pose is drawn in each frame as a translucent ghost.

    Only the final evaluation is rendered, or every one with `video_every_eval=true`. Runs after
    the round's checkpoint: a failed video only warns and never leaves a partial MP4.
    """
    evaluation, k = loop.last_evaluation, loop.counters.iteration
    if not cfg.video or evaluation is None or not evaluation.rollouts:
        return
    final = loop.finished(schedule_of(cfg))
    if not final and not cfg.video_every_eval:
        return
    episodes = [
        (f"eval_iter{k}_ep{j}", f"eval_ep{j}", r) for j, r in enumerate(evaluation.rollouts)
    ]
    if final:  # and the oracle's episodes from the same starts
        episodes += [
            (f"oracle_ep{j}", f"oracle_ep{j}", r) for j, r in enumerate(loop.oracle_rollouts)
        ]
    task = env_parts(cfg).task
    try:
        with VideoRecorder(
            loop.system.mj_model(),
            cfg.video_width,
            cfg.video_height,
            fps=1.0 / loop.system.control_dt,
            backend=resolve_backend(cfg.video_backend),
            track_root=root_travels(loop.system.layout.types),
            markers=task.markers(),
        ) as video:
            for stem, key, rollout in episodes:
                path = _record_episode(video, run_dir / VIDEO_DIR / f"{stem}.mp4", rollout, task)
                log.info("video: %s", path)
                recorder.log_video(f"video/{key}", path, loop.counters.env_steps)
    except RENDER_ERRORS as err:
        name = type(err).__name__
        log.warning("no video of iteration %d (%s: %s); the run goes on", k, name, err)


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
    from mbrl_delan.fit import read_fit_run  # the mocap stack: only when asked for

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


def _start_mechanics(model_cfg: DictConfig, model: DeLaN, system: System) -> None:
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


def _resolve_run(cfg: DictConfig) -> tuple[DictConfig, Path, dict[str, Any] | None, bool]:
    """The config and run dir to use, the checkpoint when resuming, and whether the command
    line changed the resumed run's config (saved only once it is checked). Writes nothing
    but an unreadable checkpoint's move aside (`load_checkpoint`'s `set_aside`)."""
    if cfg.resume is None:
        run_dir = Path(HydraConfig.get().runtime.output_dir)
        return with_sweep_group(cfg), run_dir, None, False
    run_dir = Path(cfg.resume)
    overrides = HydraConfig.get().overrides.task if HydraConfig.initialized() else []
    run_cfg, changed = resumed_config(overrides, cfg)
    for key in changed:
        log.info("resume: %s=%s", key, OmegaConf.select(run_cfg, key))
    ckpt = run_dir / CHECKPOINT_FILE
    state = None
    if ckpt.exists() or prev_path(ckpt).exists():
        state = load_checkpoint(ckpt, weights_only=False, set_aside=True)
    return run_cfg, run_dir, state, bool(changed)


@marks_crash
def train(cfg: DictConfig) -> dict[str, Any]:
    """Run (or resume) one training run; returns its summary.

    When it raises, the run dir gets ``crash.json`` (see ``mbrl_delan.sweep``).
    """
    cfg, run_dir, state, changed = _resolve_run(cfg)
    cfg = validate_train_config(cfg)
    if state is None and cfg.model.get("init_from") is not None:
        cfg = with_fit_structure(cfg)
    _check_video(cfg)
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    run_dir.mkdir(parents=True, exist_ok=True)
    if cfg.resume is not None:
        remove_stale_temps(run_dir)
    loop, oracle = build_loop(cfg, run_dir)
    if state is None and cfg.model.get("init_from") is not None:
        _start_mechanics(cfg.model, loop.model, loop.system)
    # written once the run is built: an error found while building (a missing clip) leaves a
    # folder that a corrected rerun can use; a resume's accepted overrides stay for later ones
    if state is None or changed:
        text = OmegaConf.to_yaml(cfg, resolve=True).encode()
        atomic_write(run_dir / RUN_CONFIG, lambda f: f.write(text), keep_prev=False)
    if state is not None:
        loop.load_state_dict(state["loop"])
        set_rng_state(state["rng"])
        loop.oracle_returns, loop.warmup_done = state["oracle_returns"], state["warmup_done"]
        log.info(
            "resumed %s at iteration %d (%d env steps)",
            run_dir,
            loop.counters.iteration,
            loop.counters.env_steps,
        )
        if loop.finished(schedule_of(cfg)) and (run_dir / SUMMARY_FILE).is_file():
            resume_metrics(run_dir / METRICS_FILE, loop.counters.iteration, loop.last_round)
            log.info("the run is finished: nothing to run, its results are left as they are")
            summary = json.loads((run_dir / SUMMARY_FILE).read_text(encoding="utf-8"))
            if "gap_closed" not in summary or "eval_steps_median" not in summary:
                summary = _complete_summary(cfg, run_dir, loop, summary)  # an older run's
            _print_summary(run_dir, summary)
            return summary
    recorder = Recorder(
        run_dir,
        cfg.logger.backend,
        cfg.logger.project,
        cfg.logger.group,
        OmegaConf.to_container(cfg, resolve=True),
        resume_iteration=loop.counters.iteration if state else None,
        step_key="env_steps",
        last_record=loop.last_round,
        wandb_options=WandbOptions.of(cfg.logger),
    )
    with recorder:
        _run(cfg, run_dir, loop, oracle, recorder)
        summary = _summary(cfg, run_dir, loop)
        recorder.write_summary(summary)
        for path in plot_run(run_dir):
            recorder.log_image(path.stem, path)
        recorder.log_artifact(run_dir / CHECKPOINT_FILE)
    _print_summary(run_dir, summary)
    return summary


def _complete_summary(
    cfg: DictConfig, run_dir: Path, loop: MBRLLoop, summary: dict[str, Any]
) -> dict[str, Any]:
    """A finished run's summary saved before its newer fields, completed: the zero-control
    baseline (evaluated from its final evaluation's starts, then kept in its checkpoint) and
    the final evaluation's median episode length."""
    if "gap_closed" not in summary:
        loop.evaluate_zero(cfg.budget.final_eval_episodes)
        _save(run_dir, loop)
        summary = _with_zero_baseline(loop, summary)
    if "eval_steps_median" not in summary:
        summary["eval_steps_median"] = _last_evaluation(run_dir).get("eval_steps_median")
    text = json.dumps(summary, indent=2, sort_keys=True) + "\n"
    atomic_write(run_dir / SUMMARY_FILE, lambda f: f.write(text.encode("utf-8")), keep_prev=False)
    log.info("completed %s with the fields it was saved without", run_dir / SUMMARY_FILE)
    return summary


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
    )


def _run(
    cfg: DictConfig,
    run_dir: Path,
    loop: MBRLLoop,
    oracle: PlannerPolicy,
    recorder: Recorder,
) -> None:
    """`loop.run` with the entry point's hooks: metrics to the recorder, an atomic checkpoint
    after each stage, videos and a progress bar after each round."""
    by_steps = cfg.budget.env_steps is not None  # the bar counts env steps, else rounds
    bar = tqdm(
        total=cfg.budget.env_steps if by_steps else cfg.budget.iterations,
        initial=loop.counters.env_steps if by_steps else loop.counters.iteration,
        desc="mbrl",
        unit="step" if by_steps else "iter",
        disable=None,
    )

    def after_round(metrics: dict[str, Any]) -> None:
        _write_videos(cfg, run_dir, loop, recorder)
        bar.update(metrics["env_steps"] - bar.n if by_steps else 1)
        bar.set_postfix(
            steps=metrics["env_steps"],
            ret=f"{metrics['train_return']:.1f}",
            oracle=f"{metrics['oracle_return_mean']:.1f}",
        )

    hooks = LoopHooks(
        log_round=lambda metrics: recorder.log(metrics, loop.counters.iteration),
        checkpoint=lambda: _save(run_dir, loop),
        after_round=after_round,
    )
    try:
        loop.run(schedule_of(cfg), oracle, hooks)
    finally:
        bar.close()


def _summary(cfg: DictConfig, run_dir: Path, loop: MBRLLoop) -> dict[str, Any]:
    last = _last_evaluation(run_dir)
    oracle = loop.oracle_returns or []
    oracle_mean = loop.oracle_mean
    eval_mean = last.get("eval_return_mean", float("nan"))
    return _with_zero_baseline(
        loop,
        {
            "env": cfg.env.name,
            "model": cfg.model.name,
            "planner": cfg.planner.name,
            "seed": cfg.seed,
            "device": cfg.device,
            "env_steps": loop.counters.env_steps,
            "episodes": loop.counters.episodes,
            "iterations": loop.counters.iteration,
            "wall_time_s": loop.counters.wall_time_s,
            "eval_return_mean": eval_mean,
            "eval_return_std": last.get("eval_return_std"),
            "oracle_return_mean": oracle_mean,
            "oracle_return_std": float(torch.tensor(oracle).std(unbiased=False))
            if oracle
            else None,
            "fraction_of_oracle": eval_mean / oracle_mean if oracle_mean else None,
            "eval_steps_median": last.get("eval_steps_median"),
        },
    )


def _last_evaluation(run_dir: Path) -> dict[str, Any]:
    """The run's last record with evaluation figures ({} before its first)."""
    records = [r for r in read_metrics(run_dir / METRICS_FILE) if "eval_return_mean" in r]
    return records[-1] if records else {}


def _with_zero_baseline(loop: MBRLLoop, summary: dict[str, Any]) -> dict[str, Any]:
    """The summary with the zero-control baseline: `zero_torque_return_mean` R0 and
    `gap_closed` = (R - R0) / (R_oracle - R0) (None where undefined)."""
    zero = loop.zero_returns
    r0 = sum(zero) / len(zero) if zero else None
    gap = summary["oracle_return_mean"] - r0 if r0 is not None else None
    closed = (summary["eval_return_mean"] - r0) / gap if gap else None
    return summary | {"zero_torque_return_mean": r0, "gap_closed": closed}


def _print_summary(run_dir: Path, s: dict[str, Any]) -> None:
    log.info("run dir: %s", run_dir)
    log.info(
        "%s / %s / %s, seed %s: eval return %.4g +- %.2g, oracle %.4g (fraction %.3f), "
        "%d env steps, %.0f s",
        s["env"],
        s["model"],
        s["planner"],
        s["seed"],
        s["eval_return_mean"],
        s["eval_return_std"] or 0.0,
        s["oracle_return_mean"],
        s["fraction_of_oracle"] or float("nan"),
        s["env_steps"],
        s["wall_time_s"],
    )


@hydra.main(version_base="1.3", config_path="configs/train", config_name="config")
def run(cfg: DictConfig) -> float | None:
    """The Hydra task: the config was checked by `StartChecks` before the run dir existed."""
    try:
        summary = train(cfg)
    except ConfigError as err:
        log.error("config error: %s", err)
        exit_or_raise(2, err)
    except TrainingDivergedError as err:
        log.error("training diverged: %s (the last good checkpoint is kept)", err)
        if cfg.model.get("init_from") is not None:
            log.error(
                "the model started from model.init_from=%s: a DeLaN fitted on motion capture "
                "without model.armature=true can have a nearly singular M off the mocap's "
                "states, so its forward predictions blow up (docs/humanoid.md, starting from "
                "the mocap fit)",
                cfg.model.init_from,
            )
        exit_or_raise(1, err)
    except NonFiniteDataError as err:
        log.error("bad data: %s (not added to the buffer; the last checkpoint is kept)", err)
        exit_or_raise(1, err)
    except MissingPackageError as err:
        log.error("missing package: %s", err)
        exit_or_raise(2, err)
    except (CheckpointError, FileNotFoundError) as err:
        log.error("cannot resume: %s", err)
        exit_or_raise(2, err)
    return summary["eval_return_mean"]


def main() -> None:
    """``python -m mbrl_delan.train``: a config error exits 2 with one line naming it."""
    exit_on_config_errors(run)


if __name__ == "__main__":
    main()
