"""Suite `planner`: how long one control step's plan takes, against the control period.

For each world-model case in `PlannerGrid.models`, planner in `planners`, samples N in
`num_samples`, horizon H in `horizons` and iteration count in `iterations`:

- `plan_latency_ms`: milliseconds of one `PlannerPolicy.act(q0, qd0)` with `replan_every=1`,
  i.e. one full planner call from a state, warm-started from the previous plan shifted by one
  step (and, for iCEM, its shifted kept elites) exactly as in the training loop; the policy
  is called from the same state again and again, so every timed call is warm-started.
- `realtime_factor`: control period / plan latency (> 1: the planner keeps up with the
  system in real time on this machine).
- `torchrl_plan_latency_ms`: for mppi and cem, the same figure for TorchRL's own
  `torchrl.modules.planners.MPPIPlanner` / `CEMPlanner` on our `ModelEnv` (same model, N, H,
  iterations; they start every call from mean 0 and std 1: no warm start), plus its
  `realtime_factor`.
- `latency_ratio_vs_torchrl` (with `paired=true`): for mppi and cem, our plan latency divided
  by TorchRL's planner of the same kind on the eager model, both timed in alternation
  (`paired_ratio`): the median over `repeats` rounds of (ours / TorchRL's), each a
  `time_call` measurement of at least `min_time_s`. A slow spell of a shared machine then
  weighs on both sides of each ratio, where the two latency figures above are minutes apart.
  On a `_compiled` case ours is compiled and TorchRL's is not: its model is the case's eager
  twin (the same weights, from the same seed).

World-model cases (`PLANNER_MODELS`), all untrained (timing does not depend on the weights),
float32, built as ``python -m mbrl_delan.train env=pendulum model=delan`` (or
``model=ensemble``) builds them, from the config Hydra composes (`loop_config`):

- `pendulum_delan`: DeLaN on the pendulum (nv 1, control period 0.05 s), task pendulum swing-up.
- `humanoid_delan`: DeLaN on the layout of gymnasium's Humanoid-v5 (`humanoid.xml`: a free root,
  nq 7 / nv 6, and 17 hinges: nq 24, nv 23, nu 17, B from its gears), control period 0.015 s
  (frame skip 5 of 0.003 s), task `StandTask` (a stand-in: reward root height - 0.1 |a|^2,
  terminated outside heights [1, 2] m, Humanoid-v5's healthy range).
- `pendulum_ensemble`: the MLP ensemble on the pendulum, 5 particles per sequence (TSinf).
- `pendulum_oracle`: MuJoCo's true pendulum dynamics (`objectives/mujoco.py`, `mujoco.rollout` on
  torch's thread count), planners in float64 on the CPU as `train.py` builds the oracle.
- `_compiled`: the case with `accel.compile=true`; on CPU, where the rollout compiles as one
  loop, its samples are rolled out in `rollout_threads` shares on worker threads (None:
  torch's thread count, as `accel.rollout_threads: null`; records carry `rollout_threads`).

Planners are the loop's (``planner=KIND`` on ``env=pendulum``, `planner_config`) with N, H
and the iterations of the setting, num_elites capped at N.

Timing (`time_plan`): settings of one (model, planner) pair run in order of work
N x H x iterations, and each call's seconds are predicted linearly in that work from the
largest setting measured before. A call under `min_time_s`: one untimed call (the cold
start), then `time_call` (no further warm-up). A slower one: `repeats` single calls, fewer
where they would take more than `max_call_s / 2` in all (one at least), without the untimed
call when the prediction already says it is slow. A setting predicted over `max_call_s` is
recorded with `value: null` and a note, as is one that cannot be built.
"""

from __future__ import annotations

import logging
import math
import statistics
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, replace
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDict
from torch import Tensor, nn
from torchrl.modules.planners import CEMPlanner as TorchRLCEMPlanner
from torchrl.modules.planners import MPPIPlanner as TorchRLMPPIPlanner

from mbrl_delan import keys
from mbrl_delan.accelerate import CompiledStep
from mbrl_delan.benchmarks import (
    COMPILED_SUFFIX,
    GRAPH_SUFFIX,
    PLANNER_MODELS,
    BenchSettings,
    Timing,
    host_fields,
    split_plugin_case,
    synchronizer,
    time_call,
    with_options,
)
from mbrl_delan.benchmarks.records import BenchRecord
from mbrl_delan.conf.bench_schema import PlannerSuiteConfig
from mbrl_delan.conf.builders import build_model
from mbrl_delan.conf.builders import build_planner as config_build_planner
from mbrl_delan.conf.checks import CONFIG_DIR, ConfigError, compose_train_config
from mbrl_delan.envs.model_env import ModelEnv
from mbrl_delan.envs.modules import ReturnToGo
from mbrl_delan.envs.registry import make_env_parts
from mbrl_delan.models.base import WorldModel
from mbrl_delan.models.delan import DeLaN
from mbrl_delan.models.ensemble import GaussianEnsemble
from mbrl_delan.objectives.base import ObjectiveFactory
from mbrl_delan.objectives.model import model_objective_factory
from mbrl_delan.objectives.mujoco import MujocoObjectiveFactory, mujoco_objective_factory
from mbrl_delan.planners.base import SamplingPlanner
from mbrl_delan.planners.icem import ICEMPlanner
from mbrl_delan.planners.policy import PlannerPolicy
from mbrl_delan.registry import ENVS
from mbrl_delan.registry import MODELS as REGISTERED_MODELS
from mbrl_delan.registry import PLANNERS as REGISTERED_PLANNERS
from mbrl_delan.systems.external import humanoid_v5_xml
from mbrl_delan.systems.system import State, System, load_system
from mbrl_delan.tasks.base import Task

log = logging.getLogger(__name__)

SUITE = "planner"
DTYPE = torch.float32
PLANNERS = ("mppi", "cem", "icem")
TORCHRL_PLANNERS = ("mppi", "cem")
HUMANOID_FRAME_SKIP = 5  # Humanoid-v5: 5 x 0.003 s = 0.015 s per control step

# the loop's settings: ``python -m mbrl_delan.train env=pendulum`` with these groups
MODEL_CONFIGS = {"delan": "model=delan", "ensemble": "model=ensemble"}


# ----------------------------------------------------------------------------- the grid


@dataclass(frozen=True)
class Setting:
    """One planner configuration to time."""

    num_samples: int  # N
    horizon: int  # H
    iterations: int

    @property
    def work(self) -> int:
        """N x H x iterations: what a call's time is predicted from."""
        return self.num_samples * self.horizon * self.iterations

    def tag(self) -> str:
        return f"n{self.num_samples}-h{self.horizon}-i{self.iterations}"


@dataclass(frozen=True)
class PlannerGrid:
    """What the suite times: cases x planners x N x H x iterations."""

    models: tuple[str, ...] = PLANNER_MODELS
    planners: tuple[str, ...] = PLANNERS
    num_samples: tuple[int, ...] = (256, 1024, 4096)
    horizons: tuple[int, ...] = (15, 30)
    iterations: tuple[int, ...] = (1, 5)
    torchrl: bool = True
    paired: bool = False  # also `latency_ratio_vs_torchrl` (ours and TorchRL's in alternation)
    rollout_threads: int | None = None  # compiled cases on CPU (None: torch's thread count)
    compile_loop: bool = True  # compiled cases on CPU: the horizon as one loop (False: per step)

    @classmethod
    def quick(cls) -> PlannerGrid:
        """Tiny sizes for tests and smoke runs: N 64, H 5, one iteration, MPPI only, and no
        compiled cases (each compiles for 10-60 s) or CUDA-graph ones."""
        models = tuple(
            m for m in PLANNER_MODELS if COMPILED_SUFFIX not in m and not m.endswith(GRAPH_SUFFIX)
        )
        return cls(
            models=models, planners=("mppi",), num_samples=(64,), horizons=(5,), iterations=(1,)
        )

    def settings(self) -> list[Setting]:
        """Every (N, H, iterations), cheapest first."""
        grid = [
            Setting(n, h, i)
            for n in self.num_samples
            for h in self.horizons
            for i in self.iterations
        ]
        return sorted(grid, key=lambda s: (s.work, s.num_samples, s.horizon))


def grid_from_options(options: PlannerSuiteConfig, quick: bool = False) -> PlannerGrid:
    """`PlannerGrid.quick()` under `quick`, else the defaults; then every option that is not
    None replaces its field."""
    grid = PlannerGrid.quick() if quick else PlannerGrid()
    return with_options(grid, asdict(options))


# ----------------------------------------------------------------------------- cases


class StandTask(Task):
    """Timing stand-in for a humanoid task: reward = root height - 0.1 |a|^2, terminated when
    the root height leaves [1, 2] m (Humanoid-v5's healthy range)."""

    name = "stand"
    episode_len = 1000

    def __init__(self, q_start: Tensor, nv: int) -> None:
        self.q_start = q_start.double()  # (nq,) the model's qpos0
        self.nv = nv

    def reward(self, q: Tensor, qd: Tensor, action: Tensor) -> Tensor:
        return q[..., 2] - 0.1 * action.square().sum(-1)

    def terminated(self, q: Tensor, qd: Tensor) -> Tensor:
        return (q[..., 2] < 1.0) | (q[..., 2] > 2.0)

    def initial_state(self, batch_shape: tuple[int, ...], generator: torch.Generator) -> State:
        q = self.q_start.to(generator.device).expand(*batch_shape, -1).clone()
        return State(q=q, qd=q.new_zeros((*batch_shape, self.nv)))


@dataclass
class Case:
    """A system, task and world model (None: the MuJoCo oracle) and the start state."""

    name: str
    system: System
    task: Task
    model: WorldModel | None
    particles: int
    q0: Tensor  # (nq,) float64 on the CPU
    qd0: Tensor  # (nv,)
    compile: bool = False  # torch.compile each control step (ours) and the model step (TorchRL)
    cuda_graph: bool = False  # replay each rollout from a CUDA graph (ours, on CUDA only)


def loop_config(*overrides: str) -> DictConfig:
    """The loop's config on the pendulum (``env=pendulum``) with `overrides`."""
    return compose_train_config(["env=pendulum", *overrides])


def build_delan(system: System) -> DeLaN:
    """DeLaN as ``python -m mbrl_delan.train env=pendulum model=delan`` builds it."""
    return build_model(loop_config(MODEL_CONFIGS["delan"]).model, system)


def build_ensemble(system: System) -> GaussianEnsemble:
    """The ensemble as ``python -m mbrl_delan.train env=pendulum model=ensemble`` builds it."""
    return build_model(loop_config(MODEL_CONFIGS["ensemble"]).model, system)


def model_config(kind: str) -> DictConfig:
    """The loop's `model=kind` on the pendulum; a plugin's model without a YAML file among the
    loop's: its schema's defaults (or none but its name, for a model without a schema)."""
    if (CONFIG_DIR / "model" / f"{kind}.yaml").is_file():
        return loop_config(f"model={kind}").model
    schema = REGISTERED_MODELS[kind].schema
    cfg = OmegaConf.structured(schema) if schema is not None else OmegaConf.create({})
    cfg.name = kind
    if "particles" not in cfg:
        cfg.particles = 1
    return cfg


def make_case(name: str, device: torch.device, seed: int = 0) -> Case:
    """The world-model case `name` (one of `PLANNER_MODELS`, or ``<env>_<model>`` for a
    plugin's registered model on a registered env), its model on `device`."""
    torch.manual_seed(seed)
    graph = name.endswith(GRAPH_SUFFIX)
    compiled = name.removesuffix(GRAPH_SUFFIX).endswith(COMPILED_SUFFIX)
    name_base = name.removesuffix(GRAPH_SUFFIX).removesuffix(COMPILED_SUFFIX)
    if name_base == "humanoid_delan":
        system = load_system(humanoid_v5_xml(), frame_skip=HUMANOID_FRAME_SKIP, name="humanoid")
        task: Task = StandTask(torch.from_numpy(system.mj_model().qpos0.copy()), system.nv)
    else:
        parts = make_env_parts("pendulum")
        system, task = parts.system, parts.task
    start = task.initial_state((), torch.Generator().manual_seed(seed))
    model: WorldModel | None
    particles = loop_config(MODEL_CONFIGS["delan"]).model.particles
    if name == "pendulum_oracle":
        model = None
    elif name == "pendulum_ensemble":
        model = build_ensemble(system)
        particles = loop_config(MODEL_CONFIGS["ensemble"]).model.particles
    elif name not in PLANNER_MODELS:  # <env>_<a plugin's model>
        env, kind = split_plugin_case(name, tuple(ENVS.names()))
        parts = make_env_parts(env)
        system, task = parts.system, parts.task
        start = task.initial_state((), torch.Generator().manual_seed(seed))
        cfg = model_config(kind)
        model, particles = build_model(cfg, system), cfg.particles
    else:
        model = build_delan(system)
    if model is not None:
        model = model.to(device=device, dtype=DTYPE).eval()
    return Case(
        name, system, task, model, particles, start.q, start.qd, compile=compiled, cuda_graph=graph
    )


# ----------------------------------------------------------------------------- planners


def planner_config(kind: str, setting: Setting) -> DictConfig:
    """The loop's `planner=kind` with the setting's N, H and iterations (num_elites <= N); a
    plugin's planner without a YAML file among the loop's: its schema's defaults."""
    n, h, i = setting.num_samples, setting.horizon, setting.iterations
    if not (CONFIG_DIR / "planner" / f"{kind}.yaml").is_file():
        return _schema_planner_config(kind, setting)
    overrides = [f"planner={kind}", f"planner.num_samples={n}", f"planner.horizon={h}"]
    overrides.append(f"planner.iterations={i}")
    elites = loop_config(f"planner={kind}").planner.get("num_elites")
    if elites is not None:
        overrides.append(f"planner.num_elites={min(elites, n)}")
    return loop_config(*overrides).planner


def _schema_planner_config(kind: str, setting: Setting) -> DictConfig:
    """A registered planner's config from its schema's defaults and the setting."""
    schema = REGISTERED_PLANNERS[kind].schema
    if schema is None:
        raise ConfigError(
            f"planners: {kind!r} has neither a YAML file nor a schema with defaults to time it at"
        )
    cfg = OmegaConf.structured(schema)
    cfg.name, cfg.num_samples = kind, setting.num_samples
    cfg.horizon, cfg.iterations = setting.horizon, setting.iterations
    return cfg


def build_planner(
    kind: str, setting: Setting, system: System, dtype: torch.dtype
) -> SamplingPlanner:
    """Our planner `kind` as the loop builds it (`planner_config`)."""
    return config_build_planner(planner_config(kind, setting), system, dtype)


def model_steps_per_call(planner: SamplingPlanner, particles: int) -> int:
    """World-model steps (of one sample each) in one `plan` call: sum_i N_i x P x H."""
    if isinstance(planner, ICEMPlanner):
        population = sum(planner.population(i) for i in range(planner.iterations))
    else:
        population = planner.num_samples * planner.iterations
    return population * particles * planner.horizon


def build_torchrl_planner(kind: str, setting: Setting, env: ModelEnv) -> nn.Module:
    """TorchRL's planner `kind` on `env`: CEM with top_k = our num_elites; MPPI over all N
    samples with TorchRL's temperature (a multiplier of the return) = 1 / ours."""
    n, h, i = setting.num_samples, setting.horizon, setting.iterations
    ours = planner_config(kind, setting)
    if kind == "cem":
        top_k = ours.num_elites
        return TorchRLCEMPlanner(
            env, planning_horizon=h, optim_steps=i, num_candidates=n, top_k=top_k
        )
    temperature = 1.0 / ours.temperature
    return TorchRLMPPIPlanner(
        env,
        ReturnToGo(),
        temperature=temperature,
        planning_horizon=h,
        optim_steps=i,
        num_candidates=n,
        top_k=n,
    )


# ----------------------------------------------------------------------------- timing


@dataclass
class Measured:
    """A timed planner call, or why it was not timed."""

    timing: Timing | None
    note: str | None = None


class LatencyPredictor:
    """Predicts a call's seconds linearly in `Setting.work` from the largest setting measured."""

    def __init__(self) -> None:
        self.work = 0
        self.seconds = 0.0

    def predict(self, setting: Setting) -> float:
        return 0.0 if self.work == 0 else self.seconds * setting.work / self.work

    def observe(self, setting: Setting, seconds: float) -> None:
        if setting.work >= self.work:
            self.work, self.seconds = setting.work, seconds


def _seconds(call: Callable[[], object], sync: Callable[[], None]) -> float:
    """Seconds of one call."""
    sync()
    start = time.perf_counter()
    call()
    sync()
    return time.perf_counter() - start


def time_plan(
    call: Callable[[], object],
    predicted: float,
    bench: BenchSettings,
    sync: Callable[[], None],
    compiles: bool = False,
) -> Timing:
    """Time `call` as the module docstring says; `predicted`: its seconds, 0 if unknown.

    Fast calls (predicted and measured under `min_time_s`): one untimed call, then
    `time_call`. Slow ones: `repeats` single calls, fewer where they would take more than
    `max_call_s / 2` in all (at least one); the untimed call is left out when the prediction
    already says the call is slow (the code path is warm from the smaller settings, and a
    cold-started plan costs what a warm-started one does). A call that `compiles` (its first
    call for a new batch size compiles graphs for seconds) always gets the untimed call, and a
    second one whose time, without compiling, sets the number of repeats.
    """
    estimate = predicted
    if predicted < bench.timing.min_time_s or compiles:
        estimate = _seconds(call, sync)  # untimed: the cold start
        if compiles:
            estimate = _seconds(call, sync)  # untimed: the first call compiled
        if estimate < bench.timing.min_time_s:
            return time_call(call, replace(bench.timing, warmup=0), sync)
    budget = bench.max_call_s / 2
    repeats = max(1, min(bench.timing.repeats, math.floor(budget / estimate)))
    samples = [_seconds(call, sync) for _ in range(repeats)]
    median = statistics.median(samples)
    return Timing(median, 1, repeats, (max(samples) - min(samples)) / median)


def measure(
    make: Callable[[], Callable[[], object]],
    setting: Setting,
    predictor: LatencyPredictor,
    bench: BenchSettings,
    sync: Callable[[], None],
    compiles: bool = False,
) -> Measured:
    """Build the call with `make()` and time it (`time_plan`), unless predicted too slow or
    unbuildable."""
    predicted = predictor.predict(setting)
    if predicted > bench.max_call_s:
        return Measured(None, f"skipped: one call predicted {predicted:.1f} s > max_call_s")
    try:
        call = make()
    except ValueError as err:  # a planner constructor's check, e.g. N too small for iCEM
        return Measured(None, f"not run: {err}")
    timing = time_plan(call, predicted, bench, sync, compiles)
    predictor.observe(setting, timing.seconds_per_call)
    return Measured(timing)


# ----------------------------------------------------------------------------- records


def latency_records(
    case_name: str,
    metric: str,
    measured: Measured,
    control_dt: float,
    device: torch.device | str,
    fields: dict[str, Any],
) -> Iterator[BenchRecord]:
    """`metric` in ms and `realtime_factor` = control_dt / latency for one setting."""
    extra = {**fields, "control_dt_s": control_dt, "latency_metric": metric}
    latency = factor = None
    if measured.timing is not None:
        seconds = measured.timing.seconds_per_call
        latency, factor = 1e3 * seconds, control_dt / seconds
        extra.update(measured.timing.fields())
        steps = fields.get("model_steps_per_call")
        if steps is not None:
            extra["model_steps_per_s"] = steps / seconds
    notes = [n for n in (fields.get("note"), measured.note) if n]
    if notes:
        extra["note"] = "; ".join(notes)
    yield BenchRecord(SUITE, case_name, metric, latency, "ms", str(device), dict(extra))
    yield BenchRecord(SUITE, case_name, "realtime_factor", factor, "x", str(device), extra)


def _threads_field(factory: ObjectiveFactory) -> dict[str, Any]:
    """{"rollout_threads": shares, "compile_loop": bool} for a model's compiling factory
    (`ModelObjectiveFactory`); {} for others."""
    if not getattr(factory, "compile", False):
        return {}
    return {"rollout_threads": factory.rollout_threads, "compile_loop": factory.whole_loop}


def _fields(case: Case, setting: Setting, planner: str, dtype: torch.dtype) -> dict[str, Any]:
    return dict(
        model=case.name,
        system=case.system.name,
        planner=planner,
        num_samples=setting.num_samples,
        horizon=setting.horizon,
        iterations=setting.iterations,
        particles=case.particles,
        nq=case.system.nq,
        nv=case.system.nv,
        nu=case.system.nu,
        dtype=str(dtype).removeprefix("torch."),
    )


def _objective_factory(
    case: Case,
    device: torch.device,
    rollout_threads: int | None = None,
    compile_loop: bool = True,
) -> ObjectiveFactory:
    if case.model is None:
        return mujoco_objective_factory(case.system, case.task, nthread=torch.get_num_threads())
    generator = torch.Generator(device=device).manual_seed(0)
    return model_objective_factory(
        case.model,
        case.task,
        particles=case.particles,
        generator=generator,
        compile=case.compile,
        cuda_graph=case.cuda_graph,
        rollout_threads=rollout_threads,
        compile_loop=compile_loop,
    )


def our_call(
    planner: SamplingPlanner, factory: ObjectiveFactory, q0: Tensor, qd0: Tensor
) -> Callable[[], Tensor]:
    """One warm-started control step of our planner from (q0, qd0), as in the loop."""
    policy = PlannerPolicy(planner, factory, replan_every=1, seed=0, device=q0.device)
    return lambda: policy.act(q0, qd0)


def our_records(
    case: Case, kind: str, grid: PlannerGrid, bench: BenchSettings, host: dict[str, Any]
) -> Iterator[BenchRecord]:
    """`plan_latency_ms` and `realtime_factor` of our planner `kind` on every setting."""
    oracle = case.model is None
    device = torch.device("cpu") if oracle else bench.device
    dtype = torch.float64 if oracle else DTYPE
    factory = _objective_factory(case, device, grid.rollout_threads, grid.compile_loop)
    q0, qd0 = case.q0.to(device, dtype), case.qd0.to(device, dtype)
    sync, predictor = synchronizer(device), LatencyPredictor()
    for setting in grid.settings():
        log.info("planner suite: %s %s %s", case.name, kind, setting.tag())
        fields = {**_fields(case, setting, kind, dtype), "implementation": "mbrl_delan", **host}

        def make(setting: Setting = setting, fields: dict[str, Any] = fields) -> Callable[[], Any]:
            planner = build_planner(kind, setting, case.system, dtype)
            fields["model_steps_per_call"] = model_steps_per_call(planner, case.particles)
            return our_call(planner, factory, q0, qd0)

        if case.cuda_graph and device.type != "cuda":
            measured = Measured(None, "not run: CUDA graphs need device=cuda")
        else:
            compiles = case.compile or case.cuda_graph  # its first call compiles or captures
            measured = measure(make, setting, predictor, bench, sync, compiles)
        fields.update(_threads_field(factory))  # as timed (shares stop if the loop ran eagerly)
        name = f"{case.name}-{kind}-{setting.tag()}"
        yield from latency_records(
            name, "plan_latency_ms", measured, case.system.control_dt, device, fields
        )
    if isinstance(factory, MujocoObjectiveFactory):
        factory.close()  # its rollout threads


def _start_tensordict(case: Case, env: ModelEnv) -> TensorDict:
    """The start state as TorchRL's planners read it (q, qd and the done flags)."""
    flag = torch.zeros(1, dtype=torch.bool, device=env.device)
    return TensorDict(
        {
            keys.Q: case.q0.to(env.device, env.state_dtype),
            keys.QD: case.qd0.to(env.device, env.state_dtype),
            keys.DONE: flag,
            keys.TERMINATED: flag.clone(),
            keys.TRUNCATED: flag.clone(),
        },
        batch_size=(),
        device=env.device,
    )


def torchrl_call(
    planner: nn.Module, start: TensorDict, actions: list[Tensor]
) -> Callable[[], Tensor]:
    """One TorchRL planning call, under inference mode as ours, appending its action (nu,)
    to `actions` (the last few are kept)."""

    def call() -> Tensor:
        with torch.inference_mode():
            action = planner(start.clone()).get(keys.ACTION)
        actions.append(action)
        del actions[:-4]
        return action

    return call


TORCHRL_NOTE = "TorchRL planner: no warm start (mean 0, std 1 every call)"


def torchrl_note(case: Case) -> str:
    """How TorchRL's planner call differs from ours on `case` (its records' `note`)."""
    if case.particles == 1:
        return TORCHRL_NOTE
    return f"{TORCHRL_NOTE}; one rollout per candidate (ours: {case.particles} particles)"


def torchrl_model(case: Case) -> WorldModel:
    """The model TorchRL's planners step: a compiled case's with each step compiled."""
    assert case.model is not None
    return CompiledStep(case.model) if case.compile else case.model


def torchrl_records(
    case: Case, kind: str, grid: PlannerGrid, bench: BenchSettings, host: dict[str, Any]
) -> Iterator[BenchRecord]:
    """`torchrl_plan_latency_ms` and `realtime_factor` of TorchRL's planner `kind`."""
    env = ModelEnv(torchrl_model(case), case.task, case.system, device=bench.device, dtype=DTYPE)
    start = _start_tensordict(case, env)
    sync, predictor = synchronizer(bench.device), LatencyPredictor()
    note = torchrl_note(case)
    for setting in grid.settings():
        log.info("planner suite: %s torchrl_%s %s", case.name, kind, setting.tag())
        fields = {**_fields(case, setting, f"torchrl_{kind}", DTYPE), "particles": 1, **host}
        fields.update(implementation="torchrl", note=note)
        fields["model_steps_per_call"] = setting.work

        actions: list[Tensor] = []  # what the timed calls returned

        def make(setting: Setting = setting, actions: list[Tensor] = actions) -> Callable[[], Any]:
            return torchrl_call(build_torchrl_planner(kind, setting, env), start, actions)

        measured = measure(make, setting, predictor, bench, sync, case.compile)
        if actions:
            fields["action_finite"] = all(bool(torch.isfinite(a).all()) for a in actions)
            if not fields["action_finite"]:
                fields["note"] += "; it returned a non-finite action"
        name = f"{case.name}-torchrl_{kind}-{setting.tag()}"
        yield from latency_records(
            name, "torchrl_plan_latency_ms", measured, case.system.control_dt, bench.device, fields
        )


# ----------------------------------------------------------------------------- paired


@dataclass(frozen=True)
class PairedTiming:
    """Ours against TorchRL's planner, timed in alternation."""

    ratio: float  # median over rounds of ours / TorchRL's seconds per call
    ours_s: float  # median of our seconds per call over the rounds
    theirs_s: float  # median of TorchRL's
    spread: float  # (max - min) / median of the rounds' ratios
    rounds: int


def paired_ratio(
    ours: Callable[[], object],
    theirs: Callable[[], object],
    rounds: int,
    seconds_per_call: Callable[[Callable[[], object]], float],
) -> PairedTiming:
    """Median over `rounds` of seconds_per_call(ours) / seconds_per_call(theirs), measured
    back to back in each round (ours first in even rounds, TorchRL's first in odd ones)."""
    pairs = []
    for r in range(rounds):
        if r % 2 == 0:
            a = seconds_per_call(ours)
            b = seconds_per_call(theirs)
        else:
            b = seconds_per_call(theirs)
            a = seconds_per_call(ours)
        pairs.append((a, b))
    ratios = [a / b for a, b in pairs]
    ratio = statistics.median(ratios)
    return PairedTiming(
        ratio=ratio,
        ours_s=statistics.median(a for a, _ in pairs),
        theirs_s=statistics.median(b for _, b in pairs),
        spread=(max(ratios) - min(ratios)) / ratio,
        rounds=rounds,
    )


PAIRED_METRIC = "latency_ratio_vs_torchrl"


def paired_records(
    case: Case, kind: str, grid: PlannerGrid, bench: BenchSettings, host: dict[str, Any]
) -> Iterator[BenchRecord]:
    """`latency_ratio_vs_torchrl` of our planner `kind` on `case` against TorchRL's on the
    case's eager model, for every setting (see the module docstring)."""
    device = bench.device
    eager = make_case(case.name.removesuffix(COMPILED_SUFFIX), device) if case.compile else case
    env = ModelEnv(eager.model, eager.task, eager.system, device=device, dtype=DTYPE)
    factory = _objective_factory(case, device, grid.rollout_threads, grid.compile_loop)
    start = _start_tensordict(eager, env)
    q0, qd0 = case.q0.to(device, DTYPE), case.qd0.to(device, DTYPE)
    sync = synchronizer(device)
    one = replace(bench.timing, repeats=1, warmup=0)

    def seconds_per_call(call: Callable[[], object]) -> float:
        return time_call(call, one, sync).seconds_per_call

    for setting in grid.settings():
        log.info("planner suite: %s %s vs torchrl %s", case.name, kind, setting.tag())
        fields = {**_fields(case, setting, kind, DTYPE), **host, "torchrl_model": eager.name}
        fields["note"] = torchrl_note(case)
        ours = our_call(build_planner(kind, setting, case.system, DTYPE), factory, q0, qd0)
        theirs = torchrl_call(build_torchrl_planner(kind, setting, env), start, [])
        _seconds(ours, sync)  # untimed: the first call compiles (a compiled case)
        slowest = max(_seconds(ours, sync), _seconds(theirs, sync))
        value = None
        if slowest > bench.max_call_s:
            fields["note"] += f"; not timed: a call took {slowest:.1f} s > max_call_s"
        else:
            paired = paired_ratio(ours, theirs, bench.timing.repeats, seconds_per_call)
            value = paired.ratio
            fields.update(
                _threads_field(factory),
                plan_latency_ms=1e3 * paired.ours_s,
                torchrl_plan_latency_ms=1e3 * paired.theirs_s,
                spread=paired.spread,
                repeats=paired.rounds,
            )
        name = f"{case.name}-{kind}_vs_torchrl-{setting.tag()}"
        yield BenchRecord(SUITE, name, PAIRED_METRIC, value, "x", str(device), fields)


# ----------------------------------------------------------------------------- the suite


def run_planner(grid: PlannerGrid, bench: BenchSettings) -> Iterator[BenchRecord]:
    """Every figure of the grid, one record at a time."""
    host = host_fields(bench.device)
    for name in grid.models:
        case = make_case(name, bench.device)
        for kind in grid.planners:
            yield from our_records(case, kind, grid, bench, host)
        if case.model is None or case.cuda_graph or not grid.torchrl:
            continue  # TorchRL's planners on a graph case would time the compiled case again
        for kind in (k for k in grid.planners if k in TORCHRL_PLANNERS):
            yield from torchrl_records(case, kind, grid, bench, host)
        for kind in (k for k in grid.planners if k in TORCHRL_PLANNERS and grid.paired):
            yield from paired_records(case, kind, grid, bench, host)


def run_planner_suite(options: PlannerSuiteConfig, bench: BenchSettings) -> Iterator[BenchRecord]:
    """The registered suite: `run_planner` on `grid_from_options`."""
    yield from run_planner(grid_from_options(options, bench.quick), bench)
