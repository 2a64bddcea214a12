"""The model-based RL loop: collect with the planner, refit the world model, evaluate.

Everything here takes built parts (envs, model, policies, buffer); only `train.py` reads
configs. `MBRLLoop.run` owns a run's schedule (the oracle, the warm-up, the rounds and when
they evaluate, `Schedule`) and calls the entry point back (`LoopHooks`) to log, checkpoint and
render. Episode resets are seeded from the episode index, so a resumed run draws the same
initial states as an uninterrupted one.
"""

from __future__ import annotations

import logging
import math
import os
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any, Protocol

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import Tensor, nn
from torchrl.data import TensorDictReplayBuffer
from torchrl.envs import EnvBase

from mbrl_delan import keys
from mbrl_delan.data.buffer import (
    add_transitions,
    all_transitions,
    buffer_state,
    episode_transitions,
    load_buffer_state,
)
from mbrl_delan.models.base import WorldModel, model_placement
from mbrl_delan.systems.posarith import differentiate_pos
from mbrl_delan.systems.system import System
from mbrl_delan.tasks.humanoid import HumanoidTask
from mbrl_delan.training.fidelity import (
    EVERY,
    CandidateRecorder,
    FidelityReference,
    RigidBodyTruth,
    build_reference,
    fidelity_metrics,
    rigid_body_metrics,
)
from mbrl_delan.training.fit import FitConfig, FitReport, fit_model

log = logging.getLogger(__name__)

EVAL_SEED_OFFSET = 1_000_003  # evaluation episodes use seeds disjoint from training ones
# a paired evaluation seeds the planner of each episode with this + the episode's seed
PLANNER_SEED_OFFSET = 7_000_001
FIDELITY_STARTS = 32  # at most about this many starts of the oracle's episode in the reference


class UniformPolicy(TensorDictModuleBase):
    """Uniformly random actions within the control range, from its own generator."""

    def __init__(self, low: Tensor, high: Tensor, seed: int) -> None:
        super().__init__()
        self.in_keys, self.out_keys = [keys.Q], [keys.ACTION]
        self.low, self.high = low.float(), high.float()
        self.generator = torch.Generator().manual_seed(seed)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        u = torch.rand((*tensordict.batch_size, *self.low.shape), generator=self.generator)
        action = self.low + (self.high - self.low) * u
        return tensordict.set(keys.ACTION, action.to(tensordict.get(keys.Q).dtype))

    def reset(self) -> None:
        """Nothing to forget between episodes (the generator keeps its stream)."""


class ZeroPolicy(TensorDictModuleBase):
    """Zero controls (clamped into the control range): the do-nothing baseline."""

    def __init__(self, low: Tensor, high: Tensor) -> None:
        super().__init__()
        self.in_keys, self.out_keys = [keys.Q], [keys.ACTION]
        self.action = torch.clamp(torch.zeros_like(low), low, high).float()

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = self.action.expand(*tensordict.batch_size, -1)
        return tensordict.set(keys.ACTION, action.to(tensordict.get(keys.Q).dtype).clone())

    def reset(self) -> None:
        """Nothing to forget."""


class EpisodePolicy(Protocol):
    """A TorchRL policy the loop runs episodes with (`PlannerPolicy`, `UniformPolicy`):
    `reset()` forgets what it kept from the last episode (a plan)."""

    def __call__(self, tensordict: TensorDictBase) -> TensorDictBase: ...

    def reset(self) -> None: ...


def run_episode(env: EnvBase, policy: EpisodePolicy, seed: int, max_steps: int) -> TensorDict:
    """One episode from a reset seeded with `seed` (a batched env: one per env, until every
    env is done). -> rollout TensorDict (T,), or (n, T) for n envs (`split_episodes`)."""
    env.set_seed(seed)
    policy.reset()
    batched = len(env.batch_size) > 0
    with torch.inference_mode():
        return env.rollout(
            max_steps, policy=policy, break_when_any_done=not batched, break_when_all_done=batched
        )


def split_episodes(rollout: TensorDictBase) -> list[TensorDictBase]:
    """The episodes of a rollout: itself for a (T,) one; for a batched env's (n, T), row i up
    to its first done step (TorchRL's partial steps repeat a finished env's last step)."""
    if rollout.ndim == 1:
        return [rollout]
    done = rollout.get(keys.NEXT_DONE).reshape(rollout.shape)  # (n, T)
    episodes = []
    for row, row_done in zip(rollout.unbind(0), done.unbind(0), strict=True):
        ends = row_done.nonzero()
        episodes.append(row[: int(ends[0]) + 1] if len(ends) else row)
    return episodes


def _position_std(system: System, q: Tensor) -> Tensor:
    """Per-DoF std (nv,) of positions q (T, nq): of q itself when nq == nv, else of the
    displacement from the first state in velocity space (quaternions have no plain std)."""
    if system.nq == system.nv:
        return q.std(0)
    start = q[:1].expand_as(q)
    return differentiate_pos(system.layout, start, q, 1.0).std(0)


def episode_return(rollout: TensorDictBase) -> float:
    return float(rollout.get(keys.NEXT_REWARD).sum())


@dataclass
class ModelError:
    """Normalised prediction error of a world model on an episode it was not trained on."""

    one_step: float
    multi_step: float
    horizon: int


@torch.no_grad()
def model_error(
    model: WorldModel, system: System, episode: TensorDictBase, horizon: int
) -> ModelError:
    """RMS of the state error, per DoF divided by the episode's state std, after 1 and H steps.

    e_k = [dq_k / std(q), dqd_k / std(qd)] with dq = q_pred (-) q_true in velocity space
    (std(q) of a free or ball joint: of the displacement from the episode's first state);
    error = sqrt(mean over starts, DoFs of e^2). The H-step error rolls the model open loop
    on the episode's own actions from every start t with t + H <= T.
    """
    place = model_placement(model)
    on = lambda key: episode[key].to(place.device, place.dtype)  # noqa: E731
    q, qd, action = on(keys.Q), on(keys.QD), on(keys.ACTION)  # (T, nq), (T, nv), (T, nu)
    q_next, qd_next = on(keys.NEXT_Q), on(keys.NEXT_QD)
    q_scale = _position_std(system, q_next).clamp_min(1e-3)  # (nv,)
    qd_scale = qd_next.std(0).clamp_min(1e-3)

    def rms(q_pred: Tensor, qd_pred: Tensor, q_true: Tensor, qd_true: Tensor) -> float:
        e_q = differentiate_pos(system.layout, q_true, q_pred, 1.0) / q_scale
        e_qd = (qd_pred - qd_true) / qd_scale
        return float(torch.cat([e_q, e_qd], -1).pow(2).mean().sqrt())

    model.eval()
    one = model.step(q, qd, action)
    h = max(1, min(horizon, q.shape[0]))
    starts = torch.arange(q.shape[0] - h + 1)
    state_q, state_qd = q[starts], qd[starts]
    for k in range(h):
        pred = model.step(state_q, state_qd, action[starts + k])
        state_q, state_qd = pred.q, pred.qd
    end = starts + h - 1
    return ModelError(
        one_step=rms(one.q, one.qd, q_next, qd_next),
        multi_step=rms(state_q, state_qd, q_next[end], qd_next[end]),
        horizon=h,
    )


@dataclass(frozen=True)
class Schedule:
    """What a run does, in order: the oracle's evaluation, the warm-up (random episodes, then
    the first fit), then rounds until `iterations` rounds are done or, with `env_steps` set,
    until a round's collection brings the env steps (the warm-up's included) to `env_steps`;
    round k evaluates `eval_episodes` episodes when `eval_every` divides k, and the last round
    `final_eval_episodes`. With `paired`, the oracle and the final evaluation plan each
    episode with the same planner seed (`PLANNER_SEED_OFFSET` + the episode's seed)."""

    oracle_episodes: int
    random_episodes: int
    iterations: int
    eval_every: int
    eval_episodes: int
    final_eval_episodes: int
    env_steps: int | None = None
    paired: bool = False  # the final evaluation and the oracle's: the same planner seeds

    def is_last(self, k: int, env_steps: int) -> bool:
        """Whether round k (1-based) ends the run, `env_steps` collected by its end."""
        return k >= self.iterations or (self.env_steps is not None and env_steps >= self.env_steps)

    def oracle_evaluations(self) -> int:
        """The oracle's episodes: with `paired`, at least the final evaluation's (the same
        starts and planner seeds)."""
        return max(self.oracle_episodes, self.final_eval_episodes if self.paired else 0)

    def evaluations_at(self, k: int, env_steps: int) -> int:
        """Evaluation episodes of round k (1-based), `env_steps` collected by its end."""
        if self.is_last(k, env_steps):
            return self.final_eval_episodes
        return self.eval_episodes if k % self.eval_every == 0 else 0


def _nothing(*_: Any) -> None:
    return None


def _mean(values: list[float]) -> float:
    return sum(values) / len(values)


@dataclass
class LoopHooks:
    """What the entry point does at the points of a run (each a no-op by default).

    log_round(metrics): a round's metrics, before its checkpoint. checkpoint(): after the
    oracle, after the warm-up and after each round (the loop's state is then complete).
    after_round(metrics): once the round is checkpointed (videos, progress).
    oracle_episode(done, total): after each of the oracle's episodes, once it is checkpointed
    (progress of the oracle phase: `done` of `total` episodes, a resumed phase from where
    it stood).
    """

    log_round: Callable[[dict[str, Any]], None] = _nothing
    checkpoint: Callable[[], None] = _nothing
    after_round: Callable[[dict[str, Any]], None] = _nothing
    oracle_episode: Callable[[int, int], None] = _nothing


@dataclass
class LoopCounters:
    iteration: int = 0
    episodes: int = 0
    env_steps: int = 0
    wall_time_s: float = 0.0


@dataclass
class Evaluation:
    returns: list[float] = field(default_factory=list)
    rollouts: list[TensorDict] = field(default_factory=list)  # the first `keep_rollouts` kept
    steps: list[int] = field(default_factory=list)  # each episode's control steps
    # the planning of the episodes evaluated in this process (not kept by a checkpoint):
    # each replan's wall time, and the control steps they served
    plan_seconds: list[float] = field(default_factory=list)
    planned_steps: int = 0

    def planning_figures(self, prefix: str = "") -> dict[str, float]:
        """`plan_ms_median` (the median replan), `plan_ms_per_control_step` (all replans over
        the control steps they served) and `plan_load_1min` (the host's load as the
        evaluation ended), each with `prefix`; {} for a policy that does not plan."""
        if not self.plan_seconds or not self.planned_steps:
            return {}
        seconds = torch.tensor(self.plan_seconds, dtype=torch.float64)
        return {
            f"{prefix}plan_ms_median": 1e3 * float(seconds.median()),
            f"{prefix}plan_ms_per_control_step": 1e3 * float(seconds.sum()) / self.planned_steps,
            f"{prefix}plan_load_1min": os.getloadavg()[0],
        }

    def episode_records(self, episode_len: int) -> dict[str, Any]:
        """Each episode's return and control steps, and the falls (episodes that ended before
        `episode_len` steps), for `metrics.jsonl`."""
        return {"eval_episode_returns": list(self.returns), "eval_episode_steps": list(self.steps),
                "eval_falls": sum(steps < episode_len for steps in self.steps)}  # fmt: skip

    def state_dict(self) -> dict[str, Any]:
        """Its returns and steps (the rollouts are not kept)."""
        return {"returns": list(self.returns), "steps": list(self.steps)}

    @classmethod
    def of_state(cls, state: dict[str, Any]) -> Evaluation:
        return cls(returns=list(state["returns"]), steps=list(state["steps"]))

    @property
    def median_steps(self) -> float:
        return float(torch.tensor(self.steps, dtype=torch.float64).median()) if self.steps else 0.0

    @property
    def mean(self) -> float:
        return float(torch.tensor(self.returns).mean()) if self.returns else float("nan")

    @property
    def std(self) -> float:
        return (
            float(torch.tensor(self.returns).std(unbiased=False)) if self.returns else float("nan")
        )


@dataclass
class PendingRound:
    """A round collected and fitted whose evaluation is under way: its metrics so far, the
    episodes it evaluates (paired or not) and those done, kept in the checkpoint after each
    episode so that a resumed run finishes the round where it stopped."""

    metrics: dict[str, Any]
    episodes: int
    paired: bool
    done: Evaluation = field(default_factory=Evaluation)

    def state_dict(self) -> dict[str, Any]:
        return {"metrics": self.metrics, "episodes": self.episodes, "paired": self.paired,
                "done": self.done.state_dict()}  # fmt: skip

    @classmethod
    def from_state_dict(cls, state: dict[str, Any]) -> PendingRound:
        done = Evaluation.of_state(state["done"])
        return cls(state["metrics"], state["episodes"], state["paired"], done)


class MBRLLoop:
    """Collect -> buffer -> fit -> plan, with evaluation and model-error diagnostics."""

    def __init__(
        self,
        env: EnvBase,
        eval_env: EnvBase,
        system: System,
        episode_len: int,
        model: WorldModel,
        optimizer: torch.optim.Optimizer | None,
        policy: EpisodePolicy,
        buffer: TensorDictReplayBuffer,
        fit_config: FitConfig,
        seed: int,
        error_horizon: int,
        model_generator: torch.Generator | None = None,
        keep_eval_rollouts: int = 0,
        fidelity_task: HumanoidTask | None = None,
        physics: System | None = None,
    ) -> None:
        self.env, self.eval_env, self.system = env, eval_env, system
        self.physics = physics or system  # what the env simulates: the fidelity's truth
        self.episode_len = episode_len
        self.model, self.optimizer, self.policy, self.buffer = model, optimizer, policy, buffer
        self.fit_config, self.seed, self.error_horizon = fit_config, seed, error_horizon
        self.fit_generator = torch.Generator().manual_seed(seed + 1)
        self.random_policy = UniformPolicy(system.ctrl_low, system.ctrl_high, seed + 2)
        self.model_generator = model_generator  # randomness of stochastic models in planning
        self.counters = LoopCounters()
        self.keep_eval_rollouts = keep_eval_rollouts  # e.g. for videos of evaluation episodes
        self.last_evaluation: Evaluation | None = None  # of the last `iterate`, if it evaluated
        self.oracle_returns: list[float] | None = None  # once `run` has evaluated the oracle
        self.oracle_steps: list[int] | None = None  # its episodes' control steps
        self.oracle_planning: dict[str, float] = {}  # its planning time (`planning_figures`)
        # zero controls from the final evaluation's starts, once `run` has evaluated them
        self.zero_returns: list[float] | None = None
        self.oracle_rollouts: list[TensorDict] = []  # its first `keep_eval_rollouts` episodes
        self.warmup_done = False  # once `run` has collected the random episodes and fitted
        self.last_round: dict[str, Any] | None = None  # the metrics of the last round run
        self.pending: PendingRound | None = None  # a round fitted, its evaluation under way
        self.oracle_done: Evaluation | None = None  # the oracle's episodes while it runs
        self.oracle_state: dict[str, Any] | None = None  # ... and its policy's state then
        self._clock: float | None = None  # inside `timed`: when its count was last brought up
        # a humanoid task: the model's fidelity on the oracle's first episode at each
        # evaluation (`training.fidelity`); its reference, once the oracle has run
        self.fidelity_task = fidelity_task
        self.fidelity_reference: FidelityReference | None = None
        self.rigid_body_truth: RigidBodyTruth | None = None  # MuJoCo's, at its states

    def run(
        self, schedule: Schedule, oracle: EpisodePolicy, hooks: LoopHooks | None = None
    ) -> None:
        """The run of `schedule` from wherever this loop stands (a resumed loop skips what its
        state says is done): the oracle's returns, the warm-up, then the rounds left."""
        hooks = hooks or LoopHooks()
        if self.oracle_returns is None:
            episodes = schedule.oracle_evaluations()
            log.info(
                "evaluating the oracle planner on MuJoCo's dynamics (%d episodes%s)",
                episodes, ", paired" if schedule.paired else "",
            )  # fmt: skip

            def episode_done() -> None:
                hooks.checkpoint()
                hooks.oracle_episode(len(self.oracle_done.steps), episodes)

            with self.timed():
                ev = self._evaluate_oracle(oracle, episodes, schedule.paired, episode_done)
            self.oracle_returns, self.oracle_rollouts = ev.returns, ev.rollouts
            self.oracle_steps, self.oracle_done, self.oracle_state = ev.steps, None, None
            self.oracle_planning = ev.planning_figures("oracle_")
            hooks.checkpoint()
        if self.zero_returns is None:
            self.evaluate_zero(schedule.final_eval_episodes)
            hooks.checkpoint()
        if not self.warmup_done:
            with self.timed():
                self.collect_random(schedule.random_episodes)
                self.fit()
            self.warmup_done = True
            hooks.checkpoint()
        while not self.finished(schedule):
            metrics = self.iterate(schedule, hooks.checkpoint)
            metrics["oracle_return_mean"] = self.oracle_mean
            self.last_round = metrics
            hooks.log_round(metrics)
            hooks.checkpoint()
            hooks.after_round(metrics)

    def finished(self, schedule: Schedule) -> bool:
        """Whether the rounds of `schedule` are done (a run has at least one round; a round
        whose evaluation is under way, `pending`, is not: its env steps are counted)."""
        k = self.counters.iteration
        return self.pending is None and k > 0 and schedule.is_last(k, self.counters.env_steps)

    def evaluate_zero(self, episodes: int) -> list[float]:
        """The zero-control baseline's returns from the evaluation starts (kept)."""
        with self.timed():
            zero = ZeroPolicy(self.system.ctrl_low, self.system.ctrl_high)
            self.zero_returns = self.evaluate(zero, episodes).returns
        return self.zero_returns

    @property
    def oracle_mean(self) -> float:
        """The mean of the oracle's returns (nan before `run` evaluated it)."""
        returns = self.oracle_returns or []
        return float(torch.tensor(returns, dtype=torch.float64).mean()) if returns else math.nan

    @contextmanager
    def timed(self) -> Iterator[None]:
        """Count the enclosed work in `counters.wall_time_s` (which survives resumes)."""
        self._clock = time.perf_counter()
        try:
            yield
        finally:
            self._count_time()
            self._clock = None

    def _count_time(self) -> None:
        """Inside `timed`: add the time since its start (or the last call) to the counter, as
        a checkpoint taken there must."""
        if self._clock is not None:
            now = time.perf_counter()
            self.counters.wall_time_s += now - self._clock
            self._clock = now

    def _collect(self, policy: EpisodePolicy) -> list[TensorDictBase]:
        """One episode per env of `self.env` into the buffer. -> the episodes, each (T_i,)."""
        rollout = run_episode(
            self.env, policy, self.seed * 10_000 + self.counters.episodes, self.episode_len
        )
        episodes = split_episodes(rollout)
        for episode in episodes:
            transitions = episode_transitions(episode, first_episode=self.counters.episodes)
            add_transitions(self.buffer, transitions)
            self.counters.episodes += 1
            self.counters.env_steps += transitions.shape[0]
        return episodes

    def collect_random(self, episodes: int) -> None:
        """At least `episodes` episodes of uniformly random actions (a batched env collects
        one per env at a time)."""
        collected = 0
        while collected < episodes:
            collected += len(self._collect(self.random_policy))

    def fit(self) -> FitReport:
        """Refit the model on the whole buffer: `identify` for a model that identifies
        itself, else gradient steps on its loss (`fit_model`)."""
        data = all_transitions(self.buffer).to(model_placement(self.model).device)
        if self.model.identifies:
            return self.model.identify(data, self.fit_generator)
        if self.optimizer is None:
            raise ValueError("a model fitted by its loss needs an optimizer")
        dropped = self.counters.env_steps - data.shape[0]  # left a full buffer, oldest first
        return fit_model(
            self.model, self.optimizer, data, self.fit_config, self.fit_generator, dropped
        )

    def evaluate(
        self, policy: EpisodePolicy, episodes: int, keep_rollouts: int = 0, paired: bool = False,
        done: Evaluation | None = None, after_episode: Callable[[], None] = _nothing,
    ) -> Evaluation:  # fmt: skip
        """Returns of `episodes` seeded episodes; the first `keep_rollouts` rollouts are kept.
        `paired`: each episode's planner seeded from the episode's seed (`PLANNER_SEED_OFFSET`),
        so two policies evaluated so meet the same starts with the same planner noise.
        `done`: the episodes evaluated already (a resumed evaluation goes on after them, and
        is extended in place); `after_episode` is called after each new one."""
        ev = done if done is not None else Evaluation()
        generator = getattr(policy, "generator", None) if paired else None
        timings: list[float] = getattr(policy, "plan_seconds", [])  # a planner's replans
        for i in range(len(ev.returns), episodes):
            s = EVAL_SEED_OFFSET + self.seed * 100 + i
            if generator is not None:
                generator.manual_seed(PLANNER_SEED_OFFSET + s)
            planned = len(timings)
            rollout = run_episode(self.eval_env, policy, s, self.episode_len)
            ev.returns.append(episode_return(rollout))
            ev.steps.append(int(rollout.shape[0]))
            ev.plan_seconds += timings[planned:]
            ev.planned_steps += int(rollout.shape[0]) if len(timings) > planned else 0
            if i < keep_rollouts:
                ev.rollouts.append(rollout)
            after_episode()
        return ev

    def _evaluate_oracle(
        self, oracle: EpisodePolicy, episodes: int, paired: bool, checkpoint: Callable[[], None]
    ) -> Evaluation:
        """The oracle's evaluation (`paired`: see `evaluate`), checkpointed after each episode
        (`oracle_done`) and continued from there; with a `fidelity_task`, its first episode's
        candidates are recorded and become the fidelity reference."""

        def save() -> None:  # the policy's generator too: an unpaired oracle goes on with it
            self.oracle_state = oracle.state_dict() if isinstance(oracle, nn.Module) else None
            self._count_time()
            checkpoint()

        if self.oracle_state is not None and isinstance(oracle, nn.Module):
            oracle.load_state_dict(self.oracle_state)
        done = self.oracle_done = self.oracle_done or Evaluation()
        factory = getattr(oracle, "objective_factory", None)
        if self.fidelity_task is not None and factory is not None and episodes and not done.steps:
            self._reference_episode(oracle, factory, paired, done)
            save()
        ev = self.evaluate(oracle, episodes, self.keep_eval_rollouts, paired, done, save)
        ev.rollouts = ev.rollouts[: self.keep_eval_rollouts]
        return ev

    def _reference_episode(
        self, oracle: EpisodePolicy, factory: Any, paired: bool, done: Evaluation
    ) -> None:
        """The oracle's first episode into `done`, its candidates recorded as the fidelity
        reference."""
        every = max(EVERY, self.episode_len // FIDELITY_STARTS)
        recorder = CandidateRecorder(factory, every, until=self.episode_len)
        oracle.objective_factory = recorder  # type: ignore[attr-defined]
        try:
            self.evaluate(oracle, 1, 1, paired, done)
        finally:
            oracle.objective_factory = factory  # type: ignore[attr-defined]
        try:
            self.fidelity_reference = build_reference(
                done.rollouts[0], recorder, self.physics, self.fidelity_task, every=every,
                seed=self.seed,
            )  # fmt: skip
        except ValueError as err:
            log.info("no fidelity figures: %s", err)

    def fidelity(self) -> dict[str, float]:
        """The model's figures on the fidelity reference (none without one); the model
        generator's stream is left where it was."""
        if self.fidelity_reference is None or self.fidelity_task is None:
            return {}
        factory = getattr(self.policy, "objective_factory", None)
        if factory is None:
            return {}
        kept = None if self.model_generator is None else self.model_generator.get_state()
        try:
            return fidelity_metrics(self.model, factory, self.fidelity_reference,
                                    self.fidelity_task)  # fmt: skip
        finally:
            if kept is not None and self.model_generator is not None:
                self.model_generator.set_state(kept)

    def iterate(
        self, schedule: Schedule, checkpoint: Callable[[], None] = _nothing
    ) -> dict[str, Any]:
        """One round: collect an on-policy episode, score the model on it, refit, evaluate (as
        many episodes as `schedule` gives this round). `checkpoint` is called once the round
        is fitted and after each evaluation episode (`pending`), so that a resumed run
        finishes the round where it stopped."""

        def save() -> None:
            self._count_time()
            checkpoint()

        with self.timed():
            if self.pending is None:
                self.pending = self._collect_and_fit(schedule)
                save()
            metrics = self._evaluate_round(self.pending, save)
        self.pending = None
        self.counters.iteration += 1
        metrics.update(
            env_steps=self.counters.env_steps,
            episodes=self.counters.episodes,
            wall_time_s=self.counters.wall_time_s,
        )
        return metrics

    def _collect_and_fit(self, schedule: Schedule) -> PendingRound:
        """A round's collection and refit, with its evaluation still to run."""
        episodes = self._collect(self.policy)
        k, steps = self.counters.iteration + 1, self.counters.env_steps
        errors = [model_error(self.model, self.system, e, self.error_horizon) for e in episodes]
        report = self.fit()
        metrics: dict[str, Any] = {  # the means over the round's episodes (one per env)
            "train_return": _mean([episode_return(e) for e in episodes]),
            "model_error_1step": _mean([e.one_step for e in errors]),
            "model_error_hstep": _mean([e.multi_step for e in errors]),
            "model_error_horizon": min(e.horizon for e in errors),
            "fit_epochs": report.epochs_run,
            "fit_train_loss": report.train_loss[-1] if report.train_loss else float("nan"),
            "fit_val_loss": report.best_val_loss,
        }
        paired = schedule.paired and schedule.is_last(k, steps)
        return PendingRound(metrics, schedule.evaluations_at(k, steps), paired)

    def _evaluate_round(self, pending: PendingRound, save: Callable[[], None]) -> dict[str, Any]:
        """The round's metrics once its evaluation (if it has one) is complete."""
        self.last_evaluation = None
        metrics = dict(pending.metrics)
        if pending.episodes == 0:
            return metrics
        ev = self.evaluate(self.policy, pending.episodes, self.keep_eval_rollouts,
                           pending.paired, pending.done, save)  # fmt: skip
        self.last_evaluation = ev
        metrics.update(
            eval_return_mean=ev.mean, eval_return_std=ev.std, eval_steps_median=ev.median_steps
        )
        metrics.update(ev.episode_records(self.episode_len))
        metrics.update(ev.planning_figures())
        if pending.paired:
            metrics.update(self.paired_figures(ev))
        metrics.update(self.fidelity())
        metrics.update(self.rigid_body_figures())
        return metrics

    def paired_figures(self, ev: Evaluation) -> dict[str, Any]:
        """The final evaluation against the oracle's episodes from the same starts and planner
        seeds: `paired_episodes`, `falls`, `oracle_falls` and `standing_return_ratio` (the
        model's mean return over the episodes where both stood over the oracle's), with the
        oracle's own returns and steps per episode."""
        n = min(len(ev.returns), len(self.oracle_returns or []))
        returns, steps = list((self.oracle_returns or [])[:n]), list((self.oracle_steps or [])[:n])
        full = self.episode_len
        both = [i for i in range(n) if ev.steps[i] >= full and steps[i] >= full]
        ratio = (sum(ev.returns[i] for i in both) / sum(returns[i] for i in both)
                 if both else math.nan)  # fmt: skip
        return {
            "paired_episodes": n, "falls": sum(s < full for s in ev.steps[:n]),
            "oracle_falls": sum(s < full for s in steps), "both_stood": len(both),
            "standing_return_ratio": ratio, "oracle_episode_returns": returns,
            "oracle_episode_steps": steps,
        }  # fmt: skip

    def rigid_body_figures(self) -> dict[str, float]:
        """The model's rigid-body figures on the fidelity reference's states (none without a
        reference or a rigid body)."""
        if self.fidelity_reference is None:
            return {}
        if self.rigid_body_truth is None:
            q = self.fidelity_reference.q
            self.rigid_body_truth = RigidBodyTruth.of(self.physics, q[: q.shape[0] // 2],
                                                      self.system)  # fmt: skip
        return rigid_body_metrics(self.model, self.rigid_body_truth)

    def state_dict(self) -> dict[str, Any]:
        return {
            "model": self.model.state_dict(),
            "optimizer": None if self.optimizer is None else self.optimizer.state_dict(),
            "policy": self.policy.state_dict(),
            "buffer": buffer_state(self.buffer),
            "counters": vars(self.counters).copy(),
            "last_round": self.last_round,
            "pending": None if self.pending is None else self.pending.state_dict(),
            "oracle_done": None if self.oracle_done is None else self.oracle_done.state_dict(),
            "oracle_state": self.oracle_state,
            "oracle_planning": self.oracle_planning,
            "zero_returns": self.zero_returns,
            "fidelity_reference": None
            if self.fidelity_reference is None
            else self.fidelity_reference.state_dict(),
            "fit_generator": self.fit_generator.get_state(),
            "random_generator": self.random_policy.generator.get_state(),
            "model_generator": None
            if self.model_generator is None
            else self.model_generator.get_state(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.model.load_state_dict(state["model"])
        if self.optimizer is not None:
            self.optimizer.load_state_dict(state["optimizer"])
        self.policy.load_state_dict(state["policy"])
        load_buffer_state(self.buffer, state["buffer"])
        self.counters = LoopCounters(**state["counters"])
        self.last_round = state.get("last_round")  # absent from older checkpoints
        self.zero_returns = state.get("zero_returns")
        pending = state.get("pending")  # absent from older checkpoints
        self.pending = None if pending is None else PendingRound.from_state_dict(pending)
        oracle_done = state.get("oracle_done")
        self.oracle_done = None if oracle_done is None else Evaluation.of_state(oracle_done)
        self.oracle_state = state.get("oracle_state")
        self.oracle_planning = state.get("oracle_planning") or {}  # older checkpoints: none
        reference = state.get("fidelity_reference")
        if reference is not None:
            self.fidelity_reference = FidelityReference.from_state_dict(reference)
        self.fit_generator.set_state(state["fit_generator"])
        self.random_policy.generator.set_state(state["random_generator"])
        if self.model_generator is not None and state.get("model_generator") is not None:
            self.model_generator.set_state(state["model_generator"])
