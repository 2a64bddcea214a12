"""Suite `humanoid`: world models of Humanoid-v5 with contacts, by open-loop rollout error.

How well does each world model of the loop predict a real humanoid (gymnasium's Humanoid-v5:
free root + 17 hinges, contacts on, `env=humanoid_stand`'s system and task) from the same
transitions? For each training-set size n in `sizes`:

1. Data: n transitions (q, qd, action -> next q, next qd) from episodes of `env` started at
   the task's initial states, under `PDHoldPolicy`: a PD law holding the initial pose plus
   Gaussian control noise (the humanoid wobbles, steps and falls; an episode ends when the
   task terminates, the head below its fall height, or after `episode_len` steps). Test
   episodes of the same policy from other seeds (`test_transitions` in all). This is not the
   planner's on-policy data: collecting 10k-50k planner steps takes hours on a CPU.
2. Models, built as `python -m mbrl_delan.train env=humanoid_stand model=...` builds them
   (`config.build_model` on the loop's config `env=humanoid_stand model=NAME`, composed from
   `mbrl_delan/configs/train` by `model_config`): `delan`
   (DeLaN with the residual generalized force), `delan_ensemble` (5 such members) and
   `ensemble` (5 Gaussian MLPs, the PETS baseline), each fitted on the same n transitions
   with `training.fit.fit_model` (Adam, early stopping on a 10% validation split). Models
   that train on windows of transitions (DeLaN and the DeLaN ensemble) get
   `fit.rollout_steps = rollout_steps` (default 5): a one-step fit, then a fit of 5-step
   rollouts through windows of the training episodes; the MLP ensemble fits single
   transitions.
3. `rollout_error` at every horizon h: `training.loop.model_error`'s h-step error on every
   test episode (open loop on the episode's own actions from every start t with t + h <= T;
   RMS over starts and DoFs of the velocity-space state error, per DoF over the episode's
   state std), averaged over the test episodes weighted by their number of starts.

Before the models, the oracle: for each task in `oracle_tasks` (`humanoid_stand`,
`humanoid_walk`, `cmu_track`), one episode of the loop's planner (MPPI, train's
`planner/mppi.yaml` with the humanoid envs' horizon 15, temperature 0.05 and noise 0.3) on
MuJoCo's true dynamics, on the real env, from the task's initial state, for at most
`oracle_steps` control steps (default: the task's own: 1,000 standing or walking, the clip's
length for cmu_track). It ends early when the task terminates (the humanoid fell, or left
the clip's root by 0.5 m). With `oracle_method="ilqr"` (cmu_track only) the oracle is
receding-horizon iLQR on MuJoCo's derivatives with the tracking residuals instead
(`planners/tracking_residual.py`).

Records: case ``{model}-n{n}``, metric ``rollout_error`` (field ``horizon``), and
``fit_s`` (seconds of the fit, both phases), with field ``rollout_steps`` (the K it was fitted
with). Case ``oracle-{task}``: metric ``oracle_return`` (the episode's return; fields
``steps`` run, ``episode_len`` asked, ``fell``, ``mean_reward``, the planner's settings; on
cmu_track also ``tracking_errors``) and ``oracle_step_s`` (seconds per control step).
Everything runs on `bench.device` except MuJoCo.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDict, TensorDictBase

from mbrl_delan import keys
from mbrl_delan.benchmarks import (
    HUMANOID_MODELS,
    HUMANOID_ORACLE_TASKS,
    BenchSettings,
    host_fields,
    with_options,
)
from mbrl_delan.benchmarks.records import BenchRecord
from mbrl_delan.conf.bench_schema import HumanoidSuiteConfig
from mbrl_delan.conf.builders import build_model, build_planner
from mbrl_delan.conf.checks import ConfigError, compose_train_config
from mbrl_delan.envs.real import env_parts_of, make_real_env
from mbrl_delan.envs.registry import TaskOptions, make_env_parts
from mbrl_delan.models.base import WorldModel
from mbrl_delan.objectives.mujoco import ENV_PHYSICS, PlanPhysics, mujoco_objective_factory
from mbrl_delan.planners.ilqr import ILQRSettings
from mbrl_delan.planners.policy import PlannerPolicy
from mbrl_delan.planners.tracking_residual import (
    TRACKING_ILQR,
    TrackingCostWeights,
    tracking_ilqr_policy,
)
from mbrl_delan.systems.system import System
from mbrl_delan.tasks.base import Task
from mbrl_delan.tasks.tracking import MotionTracking
from mbrl_delan.training.checkpoint import CHECKPOINT_FILE, load_checkpoint
from mbrl_delan.training.fit import FitConfig, TrainingDivergedError, fit_model
from mbrl_delan.training.loop import episode_return, model_error, run_episode
from mbrl_delan.training.recorder import RUN_CONFIG

log = logging.getLogger(__name__)

SUITE = "humanoid"
MODEL_CASES = HUMANOID_MODELS
# cases that are a model group with overrides (the others: the group of their name)
CASE_GROUPS = {
    "delan_contact": ("delan", ("model.contacts=true",)),
    "delan_plain": ("delan", ("model.residual=false",)),
    "delan_contact_only": ("delan", ("model.contacts=true", "model.residual=false")),
}


@dataclass(frozen=True)
class HumanoidBenchConfig:
    """Sizes and settings of the suite (`quick`: seconds, for tests)."""

    env: str = "humanoid_stand"
    sizes: tuple[int, ...] = (10_000, 50_000)  # training transitions
    test_transitions: int = 2_000
    horizons: tuple[int, ...] = (1, 10, 30)
    models: tuple[str, ...] = MODEL_CASES
    episode_len: int = 200  # control steps at most per data episode
    kp: float = 100.0  # N m / rad: PD hold of the initial hinge angles
    kd: float = 5.0  # N m s / rad
    noise: float = 0.3  # control noise std, share of each actuator's half range
    fit: FitConfig = field(
        default_factory=lambda: FitConfig(batch_size=256, max_epochs=200, patience=10)
    )
    rollout_steps: int = 5  # fit.rollout_steps of the models that train on windows (DeLaNs)
    # the loop's `model=NAME` on `env` (train's configs, `model_config`), with these overrides
    model_overrides: dict[str, tuple[str, ...]] = field(default_factory=dict)
    seed: int = 0
    oracle_tasks: tuple[str, ...] = HUMANOID_ORACLE_TASKS
    oracle_steps: int | None = None  # control steps per oracle episode (None: the task's own)
    clips: tuple[str, ...] | None = None  # cmu_track: an oracle episode per clip (None: its own)
    # the loop's planner `oracle_method` on each oracle task's env (mbrl_delan/configs/train,
    # `oracle_config`), with these overrides
    oracle_overrides: tuple[str, ...] = ()
    # oracle_method: a sampling planner's name (mppi, cem, icem, predictive) or "ilqr": iLQR
    # on MuJoCo's derivatives (tracking tasks: their residuals, the task's w k plus body
    # points' positions and velocities in the world frame; planners/tracking_residual.py)
    oracle_method: str = "mppi"
    oracle_ilqr: ILQRSettings = TRACKING_ILQR
    oracle_tracking_weights: TrackingCostWeights = TrackingCostWeights()
    # a train run dir of `env`: its checkpointed buffer's episodes (the loop's on-policy data)
    # replace the PD-hold episodes; the last ones, `test_transitions` at least, are the test set
    data_run: str | None = None

    @classmethod
    def quick(cls) -> HumanoidBenchConfig:
        tiny = ("model.hidden=8", "model.layers=1")
        ensemble = (*tiny, "model.ensemble_size=2", "model.particles=2")
        return cls(
            sizes=(120,),
            test_transitions=60,
            horizons=(1, 5),
            episode_len=30,
            fit=FitConfig(batch_size=32, max_epochs=2, patience=None),
            rollout_steps=2,
            model_overrides={
                "delan": tiny,
                "delan_contact": tiny,
                "delan_ensemble": ensemble,
                "ensemble": ensemble,
            },  # fmt: skip
            oracle_tasks=("humanoid_stand",),
            oracle_steps=3,
            oracle_overrides=(
                "planner.num_samples=16",
                "planner.horizon=3",
                "planner.knots=2",
                "planner.iterations=1",
            ),
        )


class PDHoldPolicy:
    """ctrl = clip((kp (q0 - q) - kd qd) / gear + noise) for each actuator on its hinge.

    q0: the episode's initial hinge angles. Each actuator drives the DoF where its column of
    B (tau = B ctrl) is largest, with gear B[dof, j]; noise ~ N(0, (noise * half range)^2).
    """

    def __init__(self, system: System, kp: float, kd: float, noise: float, seed: int) -> None:
        B = system.actuation.double().numpy()  # (nv, nu)
        self.dof = np.abs(B).argmax(axis=0)  # (nu,)
        self.gear = B[self.dof, np.arange(B.shape[1])]
        self.low, self.high = system.ctrl_low.double().numpy(), system.ctrl_high.double().numpy()
        self.kp, self.kd, self.noise = kp, kd, noise
        layout = system.layout
        qpos_of_dof = dict(zip(layout.dof_adr, layout.qpos_adr, strict=True))  # hinge DoFs
        self.qpos = np.array([qpos_of_dof[d] for d in self.dof])
        self.rng = np.random.default_rng(seed)
        self.q0 = np.zeros(len(self.dof))

    def reset(self, qpos: np.ndarray) -> None:
        self.q0 = qpos[self.qpos].copy()

    def __call__(self, qpos: np.ndarray, qvel: np.ndarray) -> np.ndarray:
        torque = self.kp * (self.q0 - qpos[self.qpos]) - self.kd * qvel[self.dof]
        half = 0.5 * (self.high - self.low)
        ctrl = torque / self.gear + self.noise * half * self.rng.standard_normal(len(self.dof))
        return np.clip(ctrl, self.low, self.high)


def collect_episodes(
    system: System, task: Task, n: int, cfg: HumanoidBenchConfig, seed: int
) -> list[TensorDict]:
    """Episodes (each a TensorDict (T,) of q, qd, action, next q, next qd; float64) of
    `PDHoldPolicy` on MuJoCo, until they hold n transitions in all (the last one cut)."""
    model = system.mj_model()
    data = mujoco.MjData(model)
    policy = PDHoldPolicy(system, cfg.kp, cfg.kd, cfg.noise, seed)
    generator = torch.Generator().manual_seed(seed)
    episodes, count = [], 0
    while count < n:
        start = task.initial_state((), generator)
        mujoco.mj_resetData(model, data)
        data.qpos[:], data.qvel[:] = start.q.numpy(), start.qd.numpy()
        mujoco.mj_forward(model, data)
        policy.reset(data.qpos)
        rows: list[tuple[np.ndarray, ...]] = []
        for _ in range(min(cfg.episode_len, n - count)):
            q, qd = data.qpos.copy(), data.qvel.copy()
            data.ctrl[:] = policy(q, qd)
            mujoco.mj_step(model, data, nstep=system.frame_skip)
            rows.append((q, qd, data.ctrl.copy(), data.qpos.copy(), data.qvel.copy()))
        episode = _until_terminated(_episode(rows), task)  # one batched check per episode
        count += episode.shape[0]
        episodes.append(episode)
    return episodes


def run_episodes(run_dir: str | Path) -> list[TensorDict]:
    """The episodes (each (T,) of q, qd, action, next q, next qd; float64) in the replay
    buffer of a train run's last checkpoint, in the order they were collected."""
    path = Path(run_dir) / CHECKPOINT_FILE
    if not path.is_file():
        raise ConfigError(f"data_run={run_dir}: no {CHECKPOINT_FILE} there (a train run dir?)")
    buffer = load_checkpoint(path)["loop"]["buffer"]
    size = int(buffer["size"])
    data = TensorDict(buffer["filled"], batch_size=[size]).to(torch.float64)
    # slot order; a full buffer's oldest transition is at the writer's cursor (else it is 0)
    oldest = int(buffer["writer"].get("_cursor", 0)) % size
    data = data[(torch.arange(size) + oldest) % size]
    _, lengths = torch.unique_consecutive(data["episode"].reshape(-1), return_counts=True)
    data = data.select(keys.Q, keys.QD, keys.ACTION, keys.NEXT_Q, keys.NEXT_QD)
    return list(data.split(lengths.tolist()))


def split_run_episodes(
    run_dir: str, env: str, test_transitions: int
) -> tuple[list[TensorDict], list[TensorDict]]:
    """`run_episodes` of a run of `env`: (training episodes, the last episodes holding at
    least `test_transitions` transitions)."""
    config = Path(run_dir) / RUN_CONFIG
    ran = OmegaConf.load(config).env.name if config.is_file() else env
    if ran != env:
        raise ConfigError(f"data_run={run_dir} is a run of env={ran}, not {env}")
    episodes = run_episodes(run_dir)
    count, first_test = 0, len(episodes)
    while first_test > 1 and count < test_transitions:
        first_test -= 1
        count += episodes[first_test].shape[0]
    return episodes[:first_test], episodes[first_test:]


def first_transitions(episodes: list[TensorDict], n: int, run_dir: str) -> TensorDict:
    """The first n transitions of `episodes` (time-ordered), or a ConfigError naming how
    many there are."""
    data = torch.cat(episodes)
    if n > data.shape[0]:
        raise ConfigError(
            f"transitions={n} is more than the {data.shape[0]} training transitions of "
            f"data_run={run_dir}"
        )
    return data[:n]


def _until_terminated(episode: TensorDict, task: Task) -> TensorDict:
    """The episode up to and including its first step into a terminal state."""
    done = task.terminated(episode[keys.NEXT_Q], episode[keys.NEXT_QD])  # (T,)
    hits = done.nonzero()
    return episode[: int(hits[0]) + 1] if hits.numel() else episode


def _episode(rows: list[tuple[np.ndarray, ...]]) -> TensorDict:
    columns = zip(*rows, strict=True)
    q, qd, action, q_next, qd_next = (torch.from_numpy(np.stack(c)) for c in columns)
    return TensorDict(
        {keys.Q: q, keys.QD: qd, keys.ACTION: action, keys.NEXT_Q: q_next, keys.NEXT_QD: qd_next},
        batch_size=[q.shape[0]],
    )


@dataclass
class FittedModel:
    """A model of the suite after its fit."""

    model: WorldModel
    seconds: float  # of the fit
    rollout_steps: int  # K of its fit: cfg.rollout_steps if it trains on windows, else 1


def model_config(name: str, cfg: HumanoidBenchConfig) -> DictConfig:
    """The model group of ``python -m mbrl_delan.train env=<cfg.env> model=<name>`` (a
    `CASE_GROUPS` case: its group and overrides), with the suite's `model_overrides` for it."""
    group, own = CASE_GROUPS.get(name, (name, ()))
    overrides = [f"env={cfg.env}", f"model={group}", *own, *cfg.model_overrides.get(name, ())]
    return compose_train_config(overrides).model


def oracle_config(task_name: str, cfg: HumanoidBenchConfig) -> DictConfig:
    """The config of ``python -m mbrl_delan.train env=<task_name> planner=<oracle_method>``
    with the suite's `oracle_overrides`: its planner group, and the env's oracle physics
    (iLQR: the env's only, with the `env.*` overrides)."""
    if cfg.oracle_method == "ilqr":
        env_only = [o for o in cfg.oracle_overrides if o.startswith("env.")]
        return compose_train_config([f"env={task_name}", *env_only])
    overrides = [f"env={task_name}", f"planner={cfg.oracle_method}", *cfg.oracle_overrides]
    return compose_train_config(overrides)


def fit_world_model(
    name: str, system: System, data: TensorDict, cfg: HumanoidBenchConfig, device: torch.device
) -> FittedModel:
    """Model `name` fitted on time-ordered transitions ``data`` (N,)."""
    settings = model_config(name, cfg)
    torch.manual_seed(cfg.seed)
    model = build_model(settings, system).to(device=device, dtype=torch.float32)
    optimizer = torch.optim.Adam(
        model.parameters(), lr=settings.lr, weight_decay=settings.weight_decay
    )
    generator = torch.Generator(device=device).manual_seed(cfg.seed)
    steps = cfg.rollout_steps if model.trains_on_windows else 1
    fit_cfg = replace(cfg.fit, rollout_steps=steps)
    start = time.perf_counter()
    fit_model(model, optimizer, data.to(device=device, dtype=torch.float32), fit_cfg, generator)
    return FittedModel(model, time.perf_counter() - start, steps)


def rollout_error(
    model: WorldModel, system: System, episodes: list[TensorDict], horizon: int
) -> float | None:
    """`model_error`'s horizon-step error averaged over the episodes at least that long,
    weighted by their starts (None if no episode is)."""
    total, weight = 0.0, 0
    for episode in episodes:
        starts = episode.shape[0] - horizon + 1
        if starts < 1:
            continue
        err = model_error(model, system, episode.to(torch.float32), horizon)
        total += (err.one_step if horizon == 1 else err.multi_step) * starts
        weight += starts
    return total / weight if weight else None


@dataclass
class OracleEpisode:
    """One episode of the oracle planner on the real env."""

    ret: float  # the episode's return
    steps: int  # control steps run
    episode_len: int  # control steps asked for
    fell: bool  # it ended because the task terminated (the humanoid fell)
    seconds: float  # wall time of the episode
    tracking: dict[str, float] | None = None  # motion tracking: `tracking_errors` of the episode


def tracking_errors(task: MotionTracking, rollout: TensorDictBase) -> dict[str, float]:
    """How far an episode of `task` stayed from its reference, in metres: the root's distance
    and the end effectors' root-relative distance at each reached state q_{t+1} against
    ref_{t+1}, as means over the steps (and effectors), and the largest per-step mean."""
    q = rollout.get(keys.NEXT_Q).to(torch.float64)  # (T, nq)
    d = task.distances(q, torch.arange(q.shape[0]))
    ee = d.end_effector.mean(-1)  # (T,)
    return dict(
        root_error_m=float(d.root.mean()), root_error_max_m=float(d.root.max()),
        end_effector_error_m=float(ee.mean()), end_effector_error_max_m=float(ee.max()),
    )  # fmt: skip


def oracle_episode(
    task_name: str,
    steps: int | None,
    planner_cfg: DictConfig,
    seed: int,
    physics: PlanPhysics = ENV_PHYSICS,
    task_options: TaskOptions | None = None,
) -> OracleEpisode:
    """The planner of `planner_cfg` (a planner group) over MuJoCo's dynamics (stepped as
    `physics` says) on `task_name`'s real env (its task as `task_options` say) for at most
    `steps` control steps (None: the task's episode length), from the task's initial state
    of `seed`."""
    parts = make_env_parts(task_name, None, steps, task_options)
    try:
        planner = build_planner(planner_cfg, parts.system, torch.float64)
    except ValueError as err:  # a setting the planner refuses (knots > horizon)
        raise ConfigError(f"the oracle's planner={planner_cfg.name} on {task_name}: {err}") from err
    threads = torch.get_num_threads()  # the suite's `threads`: MuJoCo rollout threads too
    with mujoco_objective_factory(
        parts.system, parts.task, nthread=threads, physics=physics
    ) as factory:
        policy = PlannerPolicy(planner, factory, seed=seed, action_dtype=torch.float32)
        return _timed_episode(task_name, parts.task.episode_len, seed, policy, task_options)


def ilqr_oracle_episode(
    task_name: str,
    steps: int | None,
    settings: ILQRSettings,
    seed: int,
    weights: TrackingCostWeights,
    physics: PlanPhysics = ENV_PHYSICS,
    task_options: TaskOptions | None = None,
) -> OracleEpisode:
    """Receding-horizon iLQR (`settings`) on MuJoCo's dynamics (stepped as `physics` says)
    and derivatives, with the tracking task's residuals (`TrackingResidual`, `weights`), like
    `oracle_episode`."""
    parts = make_env_parts(task_name, None, steps, task_options)
    policy = tracking_ilqr_policy(
        parts.system, parts.task, torch.get_num_threads(), settings, weights, physics
    )
    try:
        return _timed_episode(task_name, parts.task.episode_len, seed, policy, task_options)
    finally:
        policy.planner.close()


def _timed_episode(
    task_name: str,
    episode_len: int,
    seed: int,
    policy: PlannerPolicy,
    task_options: TaskOptions | None = None,
) -> OracleEpisode:
    """One episode of `policy` on the real env of `episode_len` control steps, timed."""
    env = make_real_env(task_name, seed=seed, episode_len=episode_len, task_options=task_options)
    start = time.perf_counter()
    rollout = run_episode(env, policy, seed, episode_len)
    seconds = time.perf_counter() - start
    env.close()
    fell = bool(rollout[keys.NEXT_TERMINATED].any())
    task = env_parts_of(env).task
    tracking = tracking_errors(task, rollout) if isinstance(task, MotionTracking) else None
    return OracleEpisode(
        episode_return(rollout), rollout.shape[0], episode_len, fell, seconds, tracking
    )


def oracle_cases(cfg: HumanoidBenchConfig) -> Iterator[tuple[str, TaskOptions | None]]:
    """Each oracle episode's task and task options: cmu_track once per clip of `cfg.clips`."""
    for name in cfg.oracle_tasks:
        if name == "cmu_track" and cfg.clips:
            yield from ((name, {"clip": clip}) for clip in cfg.clips)
        else:
            yield name, None


def oracle_records(cfg: HumanoidBenchConfig, host: dict[str, Any]) -> Iterator[BenchRecord]:
    """`oracle_return` and `oracle_step_s` of one oracle episode per task (and clip)."""
    for name, options in oracle_cases(cfg):
        log.info("humanoid suite: oracle %s episode on %s %s", cfg.oracle_method, name,
                 options or "")  # fmt: skip
        try:
            ep, settings = _oracle_run(cfg, name, options)
        except FileNotFoundError as err:  # a clip of `clips` nowhere to be found
            raise ConfigError(f"the oracle on {name} {options or ''}: {err}") from err
        fields = dict(
            env=name, **(options or {}), steps=ep.steps, episode_len=ep.episode_len,
            fell=ep.fell, mean_reward=ep.ret / ep.steps, planner=cfg.oracle_method, **settings,
            seed=cfg.seed, **(ep.tracking or {}), **host,
        )  # fmt: skip
        log.info("oracle-%s: return %.2f over %d steps%s", name, ep.ret, ep.steps,
                 " (fell)" if ep.fell else "")  # fmt: skip
        case = f"oracle-{name}"
        yield BenchRecord(SUITE, case, "oracle_return", ep.ret, "return", "cpu", fields)
        step_s = ep.seconds / ep.steps
        yield BenchRecord(SUITE, case, "oracle_step_s", step_s, "s", "cpu", fields)


def _oracle_run(
    cfg: HumanoidBenchConfig, name: str, options: TaskOptions | None
) -> tuple[OracleEpisode, dict[str, Any]]:
    """The oracle's episode on task `name` and its planner settings (record fields)."""
    train_cfg = oracle_config(name, cfg)
    env = train_cfg.env
    physics = PlanPhysics(env.oracle_substeps, env.oracle_integrator)
    plan_physics = dict(
        oracle_substeps=env.oracle_substeps, oracle_integrator=env.oracle_integrator
    )
    if cfg.oracle_method == "ilqr":
        s, w = cfg.oracle_ilqr, cfg.oracle_tracking_weights
        s = replace(s, horizon=env.oracle_horizon or s.horizon)
        ep = ilqr_oracle_episode(name, cfg.oracle_steps, s, cfg.seed, w, physics, options)
        return ep, dict(
            horizon=s.horizon, iterations=s.iterations, control_weight=s.control_weight,
            regularization=s.regularization, reuse_derivatives=s.reuse_derivatives,
            point_weight=w.point, point_velocity_weight=w.point_velocity, root_weight=w.root,
            **plan_physics,
        )  # fmt: skip
    p = train_cfg.planner
    ep = oracle_episode(name, cfg.oracle_steps, p, cfg.seed, physics, options)
    settings = ("num_samples", "horizon", "iterations", "knots", "interpolation", "temperature",
                "noise_std", "smoothing")  # fmt: skip
    return ep, {k: p[k] for k in settings if k in p} | plan_physics


def run_humanoid(cfg: HumanoidBenchConfig, bench: BenchSettings) -> Iterator[BenchRecord]:
    parts = make_env_parts(cfg.env)
    system, task = parts.system, parts.task
    host = host_fields(bench.device)
    yield from oracle_records(cfg, host)
    if not cfg.models:
        return
    if cfg.data_run is None:
        test = collect_episodes(system, task, cfg.test_transitions, cfg, cfg.seed + 1000)
        data_policy = f"pd_hold kp={cfg.kp} kd={cfg.kd} noise={cfg.noise}"
    else:
        train_episodes, test = split_run_episodes(cfg.data_run, cfg.env, cfg.test_transitions)
        data_policy = f"on-policy: {cfg.data_run}"
    for n in cfg.sizes:
        if cfg.data_run is None:
            train = torch.cat(collect_episodes(system, task, n, cfg, cfg.seed))
        else:
            train = first_transitions(train_episodes, n, cfg.data_run)
        fields = dict(
            env=cfg.env, transitions=n, test_transitions=sum(e.shape[0] for e in test),
            seed=cfg.seed, data_policy=data_policy, **host,
        )  # fmt: skip
        for name in cfg.models:
            log.info("humanoid suite: fitting %s on %d transitions", name, n)
            case = f"{name}-n{n}"
            try:
                fitted = fit_world_model(name, system, train, cfg, bench.device)
            except TrainingDivergedError as err:  # recorded; the other models still run
                log.error("%s: the fit diverged (%s); no rollout errors for it", case, err)
                note = {**fields, "note": f"fit diverged: {err}"}
                yield BenchRecord(SUITE, case, "fit_s", None, "s", str(bench.device), note)
                continue
            model_fields = {**fields, "rollout_steps": fitted.rollout_steps}
            yield BenchRecord(
                SUITE, case, "fit_s", fitted.seconds, "s", str(bench.device), model_fields
            )
            for h in cfg.horizons:
                value = rollout_error(fitted.model, system, test, h)
                log.info("%s: rollout_error h=%d %s", case, h, value)
                yield BenchRecord(
                    SUITE, case, "rollout_error", value, "normalised RMS", str(bench.device),
                    {**model_fields, "horizon": h},
                )  # fmt: skip


def suite_config(options: HumanoidSuiteConfig, quick: bool = False) -> HumanoidBenchConfig:
    """`HumanoidBenchConfig.quick()` under `quick`, else the defaults; then every option that
    is not None (`oracle_overrides`: added to the config's)."""
    cfg = HumanoidBenchConfig.quick() if quick else HumanoidBenchConfig()
    given = {
        "sizes": options.transitions, "models": options.models, "horizons": options.horizons,
        "rollout_steps": options.rollout_steps, "oracle_tasks": options.oracle_tasks,
        "oracle_steps": options.oracle_steps, "clips": options.clips,
        "oracle_method": options.oracle_planner, "seed": options.seed,
        "data_run": options.data_run,
        "oracle_overrides": (*cfg.oracle_overrides, *options.oracle_overrides),
    }  # fmt: skip
    return with_options(cfg, given)


def run_humanoid_suite(options: HumanoidSuiteConfig, bench: BenchSettings) -> Iterator[BenchRecord]:
    """The registered suite."""
    return run_humanoid(suite_config(options, bench.quick), bench)
