"""Suite `realtime`: milliseconds of planning per control step at the loop's own settings.

For each task in `tasks` (`humanoid_stand`, `humanoid_walk`, `pendulum`, or any registered env,
a plugin's too) and each dynamics in `models` (`mujoco`, `delan`, `tree`, `tree_delan`,
`ensemble`, or a plugin's registered model by its name), the config is the one
``python -m mbrl_delan.train env=<task> model=<dynamics>`` composes (with the suite's
`overrides`), and the policy is the one the loop builds from it (`train.build_policy`, or
`train.build_oracle` for `mujoco`):

- `mujoco`: the loop's oracle (`budget.oracle_planner`: the loop's planner on MuJoCo, or
  iLQR with the humanoid residuals; the env's `oracle_substeps` and `oracle_integrator`)
  runs one episode of at most `oracle_steps` control steps on the real env from the task's
  start of `seed`. `plan_ms_per_control_step` is the planning time per
  control step (the policy's calls only, not the env's steps); `steps_survived` is the
  number of control steps before the task terminated (the humanoid fell), or all of them.
- `delan`, `ensemble`: an untrained model (timing does not depend on the weights) in
  float32 on `device`, the DeLaN through the compiled path (`accel.compile=true`).
  `plan_ms_per_control_step` is the time of `replan_every` calls of `act` from the task's
  start state (one warm-started plan, then the stored plan's next actions) divided by
  `replan_every`, timed as `TimingConfig` says (the median over `repeats` measurements).

With `profile` a learned model's case also yields metric `step_share` per part (field `part`:
`benchmarks.profile.PARTS`): the part's share of the operator time of its eager path (the
same cycle with `accel.compile=false`), with that path's `eager_ms_per_control_step`
(`benchmarks.profile` says how the time is split).

A compiled case (`accel.compile=true`) also yields metric `compile_s`: the seconds of its
first replanning cycle, which compiles, less those of a compiled cycle, with `cached`
(every graph came from Inductor's on-disk cache: ``TORCHINDUCTOR_CACHE_DIR``, by default
``/tmp/torchinductor_$USER``, which the loop and its resumed runs read too) and the cache's
`graph_cache_hits` and `graph_cache_misses` in that cycle.

With `load` N > 0 every case is timed beside N busy processes (`busy_processes`: each a
Python loop that keeps one core busy): the planner on a host that others use.

Every record carries `task`, `dynamics`, `threads` (torch's, which are also MuJoCo's rollout
threads), `load` (the busy processes beside it), `load_cpu_s` (the CPU seconds they got) and
`load_1min` (the host's 1-minute load average when the case ends),
the planner and its `num_samples`, `iterations`, `knots`, `interpolation`,
`horizon` and `replan_every` (control steps per plan), `substeps` (the model's integrator
steps per control step; for `mujoco` the oracle's physics steps, `env.oracle_substeps`), and
the control period `control_dt_ms`.
"""

from __future__ import annotations

import logging
import os
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import torch
from omegaconf import DictConfig
from tensordict import TensorDictBase

from mbrl_delan import keys
from mbrl_delan.benchmarks import (
    REALTIME_DYNAMICS,
    REALTIME_TASKS,
    BenchSettings,
    host_fields,
    synchronizer,
    time_call,
)
from mbrl_delan.benchmarks.profile import profile_parts
from mbrl_delan.benchmarks.records import BenchRecord
from mbrl_delan.conf.bench_schema import RealtimeSuiteConfig
from mbrl_delan.conf.checks import compose_train_config
from mbrl_delan.envs.real import make_real_env
from mbrl_delan.envs.registry import make_env_parts
from mbrl_delan.planners.humanoid_residual import HUMANOID_ILQR
from mbrl_delan.planners.policy import PlannerPolicy
from mbrl_delan.systems.system import FREE, System
from mbrl_delan.training.loop import episode_return, run_episode

log = logging.getLogger(__name__)

SUITE = "realtime"
METRIC = "plan_ms_per_control_step"
SHARE_METRIC = "step_share"
COMPILE_METRIC = "compile_s"
EAGER = ("accel.compile=false",)  # the profiled path: every operator seen by the profiler
# the learned models' planning path: the DeLaN compiled, as the loop runs it with compile on
MODEL_OVERRIDES = {
    "delan": ("model=delan", "accel.compile=true"),
    "tree": ("model=tree", "accel.compile=true"),
    "tree_delan": ("model=tree_delan", "accel.compile=true"),
    "ensemble": ("model=ensemble",),
}
QUICK_STEPS = 5  # control steps of a mujoco episode under `quick`
BUSY_LOOP = "while True: pass"  # what each process of `load` runs
PLANNER_FIELDS = ("num_samples", "iterations", "knots", "interpolation", "horizon", "replan_every")


@dataclass(frozen=True)
class RealtimeConfig:
    """What the suite runs: tasks x dynamics at the loop's settings (with `overrides`)."""

    tasks: tuple[str, ...] = REALTIME_TASKS
    dynamics: tuple[str, ...] = REALTIME_DYNAMICS
    overrides: tuple[str, ...] = ()  # train-config overrides of every case
    oracle_steps: int | None = None  # control steps of the mujoco episodes (None: the task's)
    seed: int = 0
    load: int = 0  # busy processes beside each timed case
    profile: bool = False  # a learned model's case also splits its eager path into parts

    @classmethod
    def from_options(cls, options: RealtimeSuiteConfig, quick: bool = False) -> RealtimeConfig:
        """The options' choices; None keeps the default (`quick`: 5-step mujoco episodes)."""
        steps = options.oracle_steps
        return cls(
            tasks=tuple(options.tasks or REALTIME_TASKS),
            dynamics=tuple(REALTIME_DYNAMICS if options.models is None else options.models),
            overrides=tuple(options.overrides),
            oracle_steps=QUICK_STEPS if quick and steps is None else steps,
            seed=options.seed or 0,
            load=options.load,
            profile=options.profile,
        )


@dataclass
class Load:
    """The busy processes beside a timed case: how many, and the CPU seconds they got."""

    processes: int
    cpu_s: float = 0.0


@contextmanager
def busy_processes(count: int) -> Iterator[Load]:
    """`count` processes that each keep one core busy while the block runs (``python -c
    "while True: pass"``: one thread, no memory traffic), stopped after it; the `Load` it
    yields holds their CPU seconds once the block is done (each process's own, from
    `os.wait4`: not the compiler's worker processes that end meanwhile)."""
    load = Load(count)
    workers = [subprocess.Popen([sys.executable, "-c", BUSY_LOOP]) for _ in range(count)]
    try:
        yield load
    finally:
        for worker in workers:
            worker.kill()
            usage = os.wait4(worker.pid, 0)[2]
            worker.returncode = -9  # reaped above
            load.cpu_s += usage.ru_utime + usage.ru_stime


class TimedPolicy:
    """A policy whose calls are timed: `seconds` in all over `calls` calls."""

    def __init__(self, policy: PlannerPolicy) -> None:
        self.policy, self.seconds, self.calls = policy, 0.0, 0

    def __call__(self, tensordict: TensorDictBase) -> TensorDictBase:
        start = time.perf_counter()
        out = self.policy(tensordict)
        self.seconds += time.perf_counter() - start
        self.calls += 1
        return out

    def reset(self) -> None:
        self.policy.reset()


def case_config(task: str, dynamics: str, overrides: tuple[str, ...]) -> DictConfig:
    """The train config of one case: the loop's on `task`, its model (a plugin's by its name),
    then `overrides`."""
    model = MODEL_OVERRIDES.get(dynamics, () if dynamics == "mujoco" else (f"model={dynamics}",))
    return compose_train_config([f"env={task}", *model, *overrides])


def _fields(cfg: DictConfig, task: str, dynamics: str, control_dt: float) -> dict[str, Any]:
    """The case's fields; an iLQR oracle (`budget.oracle_planner=ilqr`) has no samples,
    knots or interpolation (None) and `HUMANOID_ILQR`'s iterations."""
    planner = {name: cfg.planner.get(name) for name in PLANNER_FIELDS}
    name = cfg.planner.name
    if dynamics == "mujoco" and cfg.budget.oracle_planner == "ilqr":
        name = "ilqr"
        planner.update(num_samples=None, knots=None, interpolation=None, replan_every=1)
        planner["iterations"] = HUMANOID_ILQR.iterations
    substeps = cfg.env.oracle_substeps if dynamics == "mujoco" else cfg.model.get("substeps")
    return dict(
        task=task, dynamics=dynamics, threads=torch.get_num_threads(),
        planner=name, **planner, substeps=substeps, control_dt_ms=1e3 * control_dt,
    )  # fmt: skip


def mujoco_case(cfg: DictConfig, task: str, steps: int | None, seed: int) -> tuple[float, dict]:
    """The oracle's planning ms per control step over one episode, and `steps_survived`."""
    from mbrl_delan.conf.loop import build_oracle

    parts = make_env_parts(task, None, steps)
    policy = TimedPolicy(build_oracle(cfg, parts.physics, parts.task))
    env = make_real_env(task, seed=seed, episode_len=parts.task.episode_len)
    try:
        rollout = run_episode(env, policy, seed, parts.task.episode_len)
    finally:
        env.close()
        policy.policy.objective_factory.close()
    extra = dict(
        steps_survived=int(rollout.shape[0]), episode_len=parts.task.episode_len, seed=seed,
        episode_return=episode_return(rollout), **_root_speed(parts.system, rollout),
        oracle_substeps=cfg.env.oracle_substeps, oracle_integrator=cfg.env.oracle_integrator,
    )  # fmt: skip
    return 1e3 * policy.seconds / max(policy.calls, 1), extra


def _root_speed(system: System, rollout: TensorDictBase) -> dict[str, float]:
    """A free root's mean horizontal speed and mean x velocity over the reached states, m/s
    (nothing for a system without a free root)."""
    if not system.layout.types or system.layout.types[0] != FREE:
        return {}
    velocity = rollout.get(keys.NEXT_QD)[:, 0:2].to(torch.float64)  # (T, 2) world frame
    return dict(
        mean_speed_m_s=float(torch.linalg.vector_norm(velocity, dim=-1).mean()),
        mean_forward_speed_m_s=float(velocity[:, 0].mean()),
    )


def policy_cycle(cfg: DictConfig, task: str, bench: BenchSettings,
                 seed: int) -> tuple[Callable[[], None], int]:  # fmt: skip
    """One replanning cycle of the loop's policy over an untrained model from the task's start
    of `seed` (`planner.replan_every` calls of `act`, the first a warm-started plan), and its
    length."""
    from mbrl_delan.conf.loop import build_policy, build_world_model

    parts = make_env_parts(task, None, None)
    model = build_world_model(cfg, parts.system, bench.device, torch.float32)
    generator = torch.Generator(device=bench.device).manual_seed(seed)
    policy = build_policy(cfg, parts.system, parts.task, model, generator)
    start = parts.task.initial_state((), torch.Generator().manual_seed(seed))
    q = start.q.to(bench.device, torch.float32)
    qd = start.qd.to(bench.device, torch.float32)
    policy.reset()

    def control_steps() -> None:
        for _ in range(policy.replan_every):
            policy.act(q, qd)

    return control_steps, policy.replan_every


def model_case(
    cfg: DictConfig, task: str, bench: BenchSettings, seed: int
) -> tuple[float, dict, dict | None]:
    """The loop's policy over an untrained model: ms per control step, timed over whole
    replanning cycles and divided by their length; with `accel.compile`, the first cycle's
    compile (`compile_s`: its seconds less a compiled cycle's, and whether every graph came
    from Inductor's on-disk cache), else None."""
    cycle, length = policy_cycle(cfg, task, bench, seed)
    sync = synchronizer(bench.device)
    before = graph_cache_counts()
    start = time.perf_counter()
    cycle()  # the first plan compiles
    sync()
    first_s = time.perf_counter() - start
    hits, misses = (after - was for after, was in zip(graph_cache_counts(), before, strict=True))
    timing = time_call(cycle, bench.timing, sync)
    compiled = None
    if cfg.accel.get("compile", False):
        compiled = dict(compile_s=first_s - timing.seconds_per_call, cached=hits > 0 and not misses,
                        graph_cache_hits=hits, graph_cache_misses=misses)  # fmt: skip
    return 1e3 * timing.seconds_per_call / length, timing.fields(), compiled


def graph_cache_counts() -> tuple[int, int]:
    """Inductor's on-disk graph cache so far in this process: (hits, misses)."""
    counters = torch._dynamo.utils.counters["inductor"]
    return counters["fxgraph_cache_hit"], counters["fxgraph_cache_miss"]


def profile_case(cfg: DictConfig, task: str, bench: BenchSettings,
                 seed: int) -> tuple[dict[str, float], float]:  # fmt: skip
    """Each part's share of the eager path's operator time (`benchmarks.profile`), and the
    eager path's ms per control step (timed as the case, without the profiler)."""
    cycle, length = policy_cycle(cfg, task, bench, seed)
    timing = time_call(cycle, bench.timing, synchronizer(bench.device))
    return profile_parts(cycle), 1e3 * timing.seconds_per_call / length


def share_records(case: str, device: str, fields: dict[str, Any], shares: dict[str, float],
                  eager_ms: float) -> Iterator[BenchRecord]:  # fmt: skip
    """The `step_share` records of one profiled case."""
    for part, share in shares.items():
        record = fields | {"part": part, "eager_ms_per_control_step": eager_ms}
        yield BenchRecord(SUITE, f"{case}-{part}", SHARE_METRIC, share, "share", device, record)


def run_realtime_suite(options: RealtimeSuiteConfig, bench: BenchSettings) -> Iterator[BenchRecord]:
    rt = RealtimeConfig.from_options(options, bench.quick)
    host = host_fields(bench.device)
    for task in rt.tasks:
        for dynamics in rt.dynamics:
            cfg = case_config(task, dynamics, rt.overrides)
            control_dt = make_env_parts(task, None, None).system.control_dt
            fields = _fields(cfg, task, dynamics, control_dt)
            log.info("realtime: %s on %s (%s), %d busy processes", dynamics, task, fields,
                     rt.load)  # fmt: skip
            with busy_processes(rt.load) as load:
                compiled = None
                if dynamics == "mujoco":
                    ms, extra = mujoco_case(cfg, task, rt.oracle_steps, rt.seed)
                else:
                    ms, extra, compiled = model_case(cfg, task, bench, rt.seed)
                load_1min = os.getloadavg()[0]
                profiled = None
                if rt.profile and dynamics != "mujoco":
                    eager = case_config(task, dynamics, (*rt.overrides, *EAGER))
                    profiled = profile_case(eager, task, bench, rt.seed)
            device = "cpu" if dynamics == "mujoco" else bench.device.type
            case = f"{task}-{dynamics}"
            load_fields = {"load": load.processes, "load_cpu_s": load.cpu_s,
                           "load_1min": load_1min, "overrides": list(rt.overrides)}  # fmt: skip
            yield BenchRecord(SUITE, case, METRIC, ms, "ms", device,
                              fields | load_fields | extra | host)  # fmt: skip
            if compiled is not None:
                seconds = compiled.pop("compile_s")
                yield BenchRecord(SUITE, case, COMPILE_METRIC, seconds, "s", device,
                                  fields | load_fields | compiled | host)  # fmt: skip
            if profiled is not None:
                yield from share_records(case, device, fields | load_fields | host, *profiled)
