"""The learned-model objective: returns of action sequences rolled out in a world model.

`model_objective_factory` is the learned-model counterpart of the MuJoCo oracle
(`objectives/mujoco.py`): an objective over (N, H, nu) action sequences rolled out in torch,
run eagerly or through the acceleration layer (`mbrl_delan.accelerate`).

Particle layout: N samples times P particles form a flat batch of N * P where particle p of
sample n sits at index n * P + p. An ensemble propagating flat index b with member b % E
(TSinf) thus gives particle p member p % E for every sample: with P a multiple of E every
sample is scored by every member equally often.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import torch
from torch import Tensor, while_loop

from mbrl_delan.accelerate import CompiledLoop, GraphedCalls, RolloutThreads, compile_dynamics
from mbrl_delan.models.base import Placement, WorldModel, eval_mode, model_placement
from mbrl_delan.objectives.base import (
    ObjectiveFactory,
    discounted_masked_return,
    risk_adjusted_return,
)
from mbrl_delan.rules import rule
from mbrl_delan.tasks.base import Task

log = logging.getLogger(__name__)

Transition = tuple[Tensor, Tensor, Tensor, Tensor]  # next q, next qd, reward, terminated


class ModelObjective:
    """Objective for one start state: returns of actions (N, H, nu) under the world model.

    Returns are the masked, discounted task returns scored over particles by
    `risk_adjusted_return` (mean - risk * std over the P particles; risk 0: the mean), on the
    actions' device and in their dtype. (N,)
    """

    def __init__(
        self, factory: ModelObjectiveFactory, q0: Tensor, qd0: Tensor, step: int = 0
    ) -> None:
        self.factory = factory
        self.q0 = q0  # (nq,) as given
        self.qd0 = qd0  # (nv,)
        self.step = step  # episode step of the first action (time-indexed tasks)

    def __call__(self, actions: Tensor) -> Tensor:
        if actions.ndim != 3:
            raise ValueError(f"actions must be (N, H, nu), got {tuple(actions.shape)}")
        f = self.factory
        place = f.placement(actions.device)
        flat = actions.to(place.device, place.dtype).repeat_interleave(
            f.particles, dim=0
        )  # (N*P, H, nu)
        with torch.inference_mode(), eval_mode(f.model):
            q0 = self.q0.to(place.device, place.dtype)  # (nq,)
            qd0 = self.qd0.to(place.device, place.dtype)  # (nv,)
            step = torch.tensor(self.step, dtype=torch.long, device=place.device)  # ()
            returns = f.returns(q0, qd0, flat, step)  # (N,)
        dtype = actions.dtype if actions.is_floating_point() else returns.dtype
        return returns.to(actions.device, dtype)


@dataclass
class RolloutSettings:
    """How the model objective's rollouts run (the loop's ``accel`` section extends it).

    compile: `torch.compile` the rollout (for deterministic models such as DeLaN): on CPU all
        H steps with their rewards and terminations as one compiled loop (`while_loop`), on
        CUDA each control step as one compiled call.
    cuda_graph: on a CUDA device, replay each rollout (all H steps and the returns) from a
        CUDA graph captured once per batch shape (`GraphedCalls`); with `compile`, the graph
        replays the compiled steps' kernels.
    rollout_threads: with `compile` on CPU and a deterministic model (DeLaN), the compiled
        rollouts (the loop, or one compiled call per step) run on this many shares of the
        samples at once, each in its own worker thread with one intra-op thread
        (`RolloutThreads`); 1 runs the whole batch on torch's intra-op threads. None: torch's
        thread count at construction.
    compile_loop: with `compile` on CPU, the H steps as one compiled loop where the model
        allows it (`WorldModel.loops_compile`); False: one compiled call per step.
    """

    compile: bool = False
    cuda_graph: bool = False
    rollout_threads: int | None = rule(None, low=1)
    compile_loop: bool = True


class ModelObjectiveFactory(ObjectiveFactory):
    """(q0 (nq,), qd0 (nv,)) -> `ModelObjective`: objectives over (N, H, nu) action sequences
    rolled out in the learned world model.

    Args:
        model: the world model; used in eval mode and under inference mode, on its own
            device and dtype (a model without floating parameters or buffers computes in
            float64 on the actions' device).
        task: reward and termination.
        particles: P rollouts per sample (flat index n * P + p), scored together.
        discount: per-step discount in (0, 1].
        generator: randomness of stochastic models (on the model's device).
        dtype: compute dtype override.
        risk: k in score = mean - k * std of the P particles' returns (population std, see
            `risk_adjusted_return`); 0 (default) is the plain mean, > 0 is risk-averse.
        accel: how the rollouts run (`RolloutSettings`; the loop's typed ``accel`` section);
            `changes` replace its fields (``compile=True``).
    """

    def __init__(
        self,
        model: WorldModel,
        task: Task,
        particles: int = 1,
        discount: float = 1.0,
        generator: torch.Generator | None = None,
        dtype: torch.dtype | None = None,
        risk: float = 0.0,
        accel: RolloutSettings | None = None,
        **changes: Any,
    ) -> None:
        if particles < 1:
            raise ValueError(f"particles must be >= 1, got {particles}")
        if not 0 < discount <= 1:
            raise ValueError(f"discount must be in (0, 1], got {discount}")
        if not math.isfinite(risk):
            raise ValueError(f"risk must be finite, got {risk}")
        accel = replace(accel or RolloutSettings(), **changes)
        self.model = model
        self.task = task
        self.particles = particles
        self.discount = discount
        self.generator = generator
        self.dtype = dtype
        self.risk = float(risk)
        self.compile, self.cuda_graph = accel.compile, accel.cuda_graph
        self._compiled: Callable[[Tensor, Tensor, Tensor, Tensor], Transition] | None = None
        self._compiled_loop: CompiledLoop | None = None
        # the whole horizon as one compiled loop where the model allows (False once it failed)
        self._loop_compiles = model.loops_compile and accel.compile_loop
        threads = (
            torch.get_num_threads() if accel.rollout_threads is None else accel.rollout_threads
        )
        if threads < 1:
            raise ValueError(f"rollout_threads must be >= 1, got {accel.rollout_threads}")
        # shares of a batch in parallel (the compiled loop, or one compiled call per step: both
        # release the GIL) where the model draws no random numbers (a generator shared by
        # threads would make the draws' order vary)
        shares = accel.compile and threads > 1 and model.deterministic
        self._threads = RolloutThreads(threads) if shares else None
        self._graphs = GraphedCalls(
            self._returns,
            watched=lambda: [*model.parameters(), *model.buffers()],
            generators=[generator] if generator is not None else [],
        )

    def returns(self, q0: Tensor, qd0: Tensor, actions: Tensor, step: Tensor) -> Tensor:
        """Scores of action sequences from one start, on the model's device and dtype.

        (nq,), (nv,), (N*P, H, nu) with particle p of sample n at n * P + p, episode step of
        the first action () int64 -> (N,), by the rollout `_rollout` chooses.
        """
        return self._rollout(actions.is_cuda)(q0, qd0, actions, step)

    def _rollout(self, cuda: bool) -> Callable[[Tensor, Tensor, Tensor, Tensor], Tensor]:
        """How a batch is rolled out: with `cuda_graph` on CUDA, replayed from a CUDA graph
        per shape (`GraphedCalls`); uncompiled, or compiled on CUDA (each step compiled),
        step by step (`_returns`); compiled on CPU, the compiled loop where it compiles
        (`_loop_returns`), else one compiled call per step (`_step_returns`)."""
        if self.cuda_graph and cuda:
            return self._graphs
        if not self.compile or cuda:
            return self._returns
        return self._loop_returns if self._loop_compiles else self._step_returns

    def _step_returns(self, q0: Tensor, qd0: Tensor, actions: Tensor, step: Tensor) -> Tensor:
        """One compiled call per step, with `rollout_threads` in shares (`_shared`). (N,)"""
        if self._threads is None:
            return self._returns(q0, qd0, actions, step)
        shared = lambda share: self._returns(q0, qd0, share, step)  # noqa: E731
        return self._shared(self._threads, shared, actions)

    def _shared(
        self, threads: RolloutThreads, fn: Callable[[Tensor], Tensor], actions: Tensor
    ) -> Tensor:
        """`fn` (returns of a share of the samples) on `threads`' shares of the samples (each
        with its P particles), one per worker thread, all of one size (a batch of a new size
        compiles once, not once per share size). (N*P, H, nu) -> (N,)"""
        samples = actions.unflatten(0, (-1, self.particles))  # (N, P, H, nu)
        n, k = samples.shape[0], threads.threads
        size = -(-n // k)  # samples per share, the last share padded with copies of the last
        if size * k > n:
            samples = torch.cat([samples, samples[-1:].expand(size * k - n, *samples.shape[1:])])
        shares = [s.flatten(0, 1) for s in samples.split(size)]  # one shape: one compiled graph
        return torch.cat(threads.map(fn, shares))[:n]  # (N,)

    def _loop_returns(self, q0: Tensor, qd0: Tensor, actions: Tensor, step: Tensor) -> Tensor:
        """The compiled loop on the whole batch, or with `rollout_threads` in shares (`_shared`);
        where the compiler fails it, one compiled call per step from then on. (N,)"""
        try:
            return self._compiled_loop_returns(q0, qd0, actions, step)
        except torch._dynamo.exc.TorchDynamoException as err:
            # e.g. a plugin's model whose step mutates state outside the loop's body
            self._loop_compiles = False
            reason = str(err).strip().splitlines()[0]
            log.warning("no compiled rollout loop (%s): one compiled call per step", reason)
        return self._step_returns(q0, qd0, actions, step)

    def _compiled_loop_returns(
        self, q0: Tensor, qd0: Tensor, actions: Tensor, step: Tensor
    ) -> Tensor:
        if self._compiled_loop is None:
            self._warm_up(q0, qd0, actions[:1, 0], step)
            self._compiled_loop = CompiledLoop(self._looped_returns)
        loop = self._compiled_loop
        if self._threads is None:
            return loop(q0, qd0, actions, step)
        scores = self._shared(self._threads, lambda share: loop(q0, qd0, share, step), actions)
        if loop.ran_eagerly:  # eager kernels on one thread each, serialised by the GIL
            log.warning(
                "the compiled rollout loop ran uncompiled for a share of the batch (the "
                "compiler's recompile limit: too many batch sizes); rollouts go back to one "
                "batch on torch's threads"
            )
            self.close()
            self._threads = None
        return scores

    @property
    def rollout_threads(self) -> int:
        """Shares of a batch rolled out side by side on worker threads (1: one batch)."""
        return self._threads.threads if self._threads is not None and self._in_shares() else 1

    @property
    def planning_threads(self) -> int | None:
        """Intra-op threads for a planner's own work while it plans with this factory: 1 while
        the rollouts run on worker threads (an intra-op thread of the planner's, idle between
        its parallel kernels, spins for milliseconds on a core the workers need), else None
        (leave them as they are). See `PlannerPolicy`."""
        return 1 if self._in_shares() else None

    @property
    def whole_loop(self) -> bool:
        """Whether the rollouts run as one compiled loop over the horizon (`compile` on the
        CPU, a model that allows it, `compile_loop`, and the compiler has not failed it)."""
        cpu = self.placement(torch.device("cpu")).device.type == "cpu"
        return self.compile and self._loop_compiles and cpu

    def _in_shares(self) -> bool:
        """Whether the rollouts run in shares: compiled (the loop or per step), on the CPU."""
        if self._threads is None:
            return False
        return self.placement(torch.device("cpu")).device.type == "cpu"

    def close(self) -> None:
        """Stop the rollout worker threads, if any (a later call starts them again)."""
        if self._threads is not None:
            self._threads.close()

    def _returns(self, q0: Tensor, qd0: Tensor, actions: Tensor, step: Tensor) -> Tensor:
        batch, horizon, _ = actions.shape
        if torch.is_inference_mode_enabled() and not actions.is_inference():
            # a planner's buffer made outside inference mode: its slices would be normal
            # tensors, on which a compiled transition guards and compiles a second graph
            actions = actions.clone()
        # the start as the later states are (contiguous): a compiled transition then needs
        # one graph per batch size, not a second for the first step
        q, qd = q0.expand(batch, -1).contiguous(), qd0.expand(batch, -1).contiguous()
        steps = step + torch.arange(horizon, device=actions.device)  # (H,)
        rewards, terminated = [], []
        for t in range(horizon):
            q, qd, reward, term = self.transition(q, qd, actions[:, t], steps[t])
            rewards.append(reward)  # (N*P,)
            terminated.append(term)  # (N*P,)
        returns = discounted_masked_return(
            torch.stack(rewards, dim=-1), torch.stack(terminated, dim=-1), self.discount
        )  # (N*P,)
        return risk_adjusted_return(returns.reshape(-1, self.particles), self.risk)  # (N,)

    def _looped_returns(self, q0: Tensor, qd0: Tensor, actions: Tensor, step: Tensor) -> Tensor:
        """`_returns` with the H steps in one `while_loop`, for compiling on CPU: the compiled
        loop runs every step's kernels from C++ without coming back to Python, where the
        per-step graph call (guards, wrapper, allocations) cost about 70 us a step. The
        return is accumulated step by step: r_t * discount^t while no earlier step has
        terminated (`discounted_masked_return`). On CUDA the loop's condition would be a
        device-to-host copy per step, so CUDA keeps one compiled call per step."""
        batch, horizon, nu = actions.shape
        q, qd = q0.expand(batch, -1).clone(), qd0.expand(batch, -1).clone()
        total = actions.new_zeros(batch)  # (N*P,) discounted return so far
        alive = torch.ones(batch, dtype=torch.bool, device=actions.device)  # none ended yet
        weight = actions.new_ones(())  # discount^t
        t0 = torch.zeros((), dtype=torch.long, device=actions.device)

        def not_done(t: Tensor, *_: Tensor) -> Tensor:
            return t < horizon

        def one_step(
            t: Tensor, q: Tensor, qd: Tensor, total: Tensor, alive: Tensor, weight: Tensor
        ) -> tuple[Tensor, ...]:
            action = actions.index_select(1, t.reshape(1)).reshape(batch, nu)  # (N*P, nu)
            q, qd, reward, term = self._transition(q, qd, action, step + t)
            total = total + torch.where(alive, weight * reward, torch.zeros_like(reward))
            return t + 1, q, qd, total, alive & ~term, weight * self.discount

        carried = (t0, q, qd, total, alive, weight)
        total = while_loop(not_done, one_step, carried)[3]  # (N*P,)
        return risk_adjusted_return(total.reshape(-1, self.particles), self.risk)  # (N,)

    def transition(self, q: Tensor, qd: Tensor, action: Tensor, step: Tensor) -> Transition:
        """One control step in the model and its task reward and termination.

        (B, nq), (B, nv), (B, nu), episode step of the action () int64 -> next q (B, nq),
        next qd (B, nv), reward (B,), terminated (B,). With `compile`, a `torch.compile`d
        copy (compiled on the first call and again per new batch size; about 5-40 s each on
        CPU).
        """
        if not self.compile:
            return self._transition(q, qd, action, step)
        if self._compiled is None:  # what the first call builds is built before the trace
            self._warm_up(q[0], qd[0], action[:1], step)
            self._compiled = compile_dynamics(self._transition)
        return self._compiled(q, qd, action, step)

    def _warm_up(self, q0: Tensor, qd0: Tensor, action: Tensor, step: Tensor) -> None:
        """One eager step of one sample before the loop compiles: what the model and the task
        build and cache on their first call (the tree's constants per dtype) cannot be made
        inside the loop's traced body. Its draws come from a generator of its own, so the
        planner's stay as they were."""
        spare = torch.Generator(device=action.device).manual_seed(0)
        nxt = self.model.step(q0.expand(1, -1).clone(), qd0.expand(1, -1).clone(), action,
                              generator=spare)  # fmt: skip
        self.task.reward_at(nxt.q, nxt.qd, action, step)
        self.task.terminated_at(nxt.q, nxt.qd, step)

    def _transition(self, q: Tensor, qd: Tensor, action: Tensor, step: Tensor) -> Transition:
        nxt = self.model.step(q, qd, action, generator=self.generator)
        reward = self.task.reward_at(nxt.q, nxt.qd, action, step)
        return nxt.q, nxt.qd, reward, self.task.terminated_at(nxt.q, nxt.qd, step)

    def placement(self, fallback_device: torch.device) -> Placement:
        """Where to compute: the model's device and dtype (or the override dtype)."""
        place = model_placement(self.model, fallback_device=fallback_device)
        return Placement(place.device, self.dtype or place.dtype)

    @property
    def time_indexed(self) -> bool:
        """Its task depends on the episode step: call it with `step=`."""
        return self.task.time_indexed

    def __call__(self, q0: Tensor, qd0: Tensor, step: int = 0) -> ModelObjective:
        """The objective from state (q0, qd0) at episode step `step` (time-indexed tasks)."""
        return ModelObjective(self, q0, qd0, step)


model_objective_factory = ModelObjectiveFactory  # the name the loop and its docs use
