"""A planner as a receding-horizon TorchRL policy: TensorDict with q, qd in, action out."""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Callable, Iterator
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import Tensor

from mbrl_delan import keys
from mbrl_delan.objectives.base import ObjectiveFactory, as_objective_factory
from mbrl_delan.planners.base import Planner

log = logging.getLogger(__name__)


def read_state(tensordict: TensorDictBase, policy: str) -> tuple[Tensor, Tensor]:
    """The unbatched state q (nq,), qd (nv,) a receding-horizon `policy` acts on."""
    missing = [key for key in (keys.Q, keys.QD) if key not in tensordict.keys()]
    if missing:
        raise KeyError(
            f"{policy} reads the keys {', '.join(map(repr, missing))}, which the env's "
            f"tensordict lacks (it has {', '.join(map(repr, sorted(tensordict.keys())))}): "
            "an env of its own gives its generalized positions and velocities as q and qd "
            "(a TorchRL transform can rename them)"
        )
    q, qd = tensordict.get(keys.Q), tensordict.get(keys.QD)
    if q.ndim != 1 or qd.ndim != 1:
        raise ValueError(
            f"{policy} needs unbatched q (nq,) and qd (nv,), got {tuple(q.shape)} "
            f"and {tuple(qd.shape)}"
        )
    return q, qd


def episode_starts(tensordict: TensorDictBase) -> bool:
    """First step of an episode, by TorchRL's InitTracker or StepCounter (if present)."""
    is_init = tensordict.get(keys.IS_INIT, None)
    if is_init is not None:
        return bool(is_init.reshape(-1)[0])
    step_count = tensordict.get(keys.STEP_COUNT, None)
    return step_count is not None and int(step_count.reshape(-1)[0]) == 0


@contextlib.contextmanager
def intra_op_threads(threads: int | None) -> Iterator[None]:
    """torch's intra-op threads set to `threads` for the block, then put back (None: left
    as they are). OpenMP's and MKL's counts are the calling thread's; torch's default for
    threads started inside the block is the block's count."""
    if threads is None:
        yield
        return
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(before)


class PlannerPolicy(TensorDictModuleBase):
    """Receding-horizon control with a planner: a sampling planner (CEM, iCEM, MPPI) over a
    model or MuJoCo objective, or iLQR on MuJoCo (`ILQRPlanner` with `ILQRStarts`).

    Every `replan_every` control steps it builds an objective for the current state with
    `objective_factory(q, qd)` (`objective_factory(q, qd, step=t)`, t the episode step, when
    the factory's `time_indexed` is true: a task that follows a reference in time) and plans,
    warm-started from the previous plan shifted by the steps executed since; in between it
    executes the stored plan open loop.

    Call `reset()` at the start of each episode (it is also called automatically when the
    input carries TorchRL's `step_count` equal to 0). `state_dict()` holds the current plan,
    the step counter and the generator state, so a checkpointed run resumes identically.

    A batched tensordict (B envs: TorchRL's `SerialEnv`, `ParallelEnv`) gets one plan per env:
    env i is acted on by a policy of its own like this one, seeded `seed + i` (env 0's acts as
    this policy would on that env alone), whose episodes start by the env's own `is_init` or
    `step_count`.

    A factory with a `planning_threads` count (rollouts on worker threads) has the plan run
    on that many intra-op threads (`intra_op_threads`).

    Args:
        planner: the optimiser (`Planner`: CEM, MPPI, ..., iLQR).
        objective_factory: (q0 (nq,), qd0 (nv,)) -> what the planner plans on: an objective
            over (N, H, nu) actions for a sampling planner.
        replan_every: control steps between plans (1 = MPC), 1 <= replan_every <= horizon.
        seed: seed of the policy's own generator.
        device: where plans are sampled (the objective receives actions there).
        action_dtype: dtype of the written action; None uses the dtype of q.
    """

    def __init__(
        self,
        planner: Planner,
        objective_factory: ObjectiveFactory | Callable[..., Any],
        replan_every: int = 1,
        seed: int = 0,
        device: torch.device | str = "cpu",
        action_dtype: torch.dtype | None = None,
    ) -> None:
        super().__init__()
        if not 1 <= replan_every <= planner.horizon:
            raise ValueError(
                f"replan_every must be in [1, horizon={planner.horizon}], got {replan_every}"
            )
        self.in_keys = [keys.Q, keys.QD]
        self.seed = seed
        self._per_env: list[PlannerPolicy] = []  # a batched input's envs (`_forward_batched`)
        self.out_keys = [keys.ACTION]
        self.planner = planner
        self.objective_factory = objective_factory
        self.replan_every = replan_every
        self.plan_device = torch.device(device)
        self.action_dtype = action_dtype
        self.generator = torch.Generator(device=self.plan_device)
        self.generator.manual_seed(seed)
        self._plan: Tensor | None = None  # (H, nu) the plan being executed
        self._steps_since_plan = 0
        self._episode_step = 0  # control steps since `reset`
        self._carried: dict[str, Tensor] = {}  # planner state for the next warm start
        self.last_result: Any = None  # what the last `plan` call returned
        self.plan_seconds: list[float] = []  # wall time of each replan (objective + plan)

    def reset(self) -> None:
        """Forget the plan (start of an episode); the generator keeps its stream."""
        self._plan = None
        self._steps_since_plan = 0
        self._episode_step = 0
        self._carried = {}
        self.last_result = None
        for policy in self._per_env:
            policy.reset()

    @property
    def plan_mean(self) -> Tensor | None:
        """The plan being executed, (H, nu), or None before the first step."""
        return self._plan

    def act(self, q: Tensor, qd: Tensor) -> Tensor:
        """The action for state (q (nq,), qd (nv,)), replanning when due. -> (nu,)"""
        if self._plan is None or self._steps_since_plan >= self.replan_every:
            self._replan(q, qd)
        action = self._plan[self._steps_since_plan]
        self._steps_since_plan += 1
        self._episode_step += 1
        return action

    def _replan(self, q: Tensor, qd: Tensor) -> None:
        start = time.perf_counter()
        self._plan_once(q, qd)
        if self.plan_device.type == "cuda":  # the plan's kernels done, as its action needs
            torch.cuda.synchronize(self.plan_device)
        self.plan_seconds.append(time.perf_counter() - start)

    def _plan_once(self, q: Tensor, qd: Tensor) -> None:
        if self._plan is None:
            init = self.planner.initial_mean(device=self.plan_device)
        else:
            init = self.planner.shift(self._plan, self._steps_since_plan)
        factory = self.objective_factory
        objective = factory(q, qd, step=self._episode_step if factory.time_indexed else 0)
        warm = {}
        if self._plan is not None:
            warm = self.planner.warm_start(self._carried, self._steps_since_plan)
        with intra_op_threads(self.objective_factory.planning_threads):
            result = self.planner.plan(objective, init, self.generator, **warm)
        if log.isEnabledFor(logging.DEBUG):  # float() syncs with the device
            log.debug("planned: best return %.4g", float(result.best_return))
        self.last_result = result
        self._plan = result.mean
        self._carried = self.planner.carry(result)
        self._steps_since_plan = 0

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        if tensordict.batch_dims:
            return self._forward_batched(tensordict)
        q, qd = read_state(tensordict, "PlannerPolicy")
        if episode_starts(tensordict):
            self.reset()
        action = self.act(q, qd)
        device = tensordict.device if tensordict.device is not None else q.device
        dtype = self.action_dtype or q.dtype
        tensordict.set(keys.ACTION, action.to(device=device, dtype=dtype).clone())
        return tensordict

    def _forward_batched(self, tensordict: TensorDictBase) -> TensorDictBase:
        """One action per env of a batched tensordict (*B): each env's own policy. An env
        that TorchRL's partial steps leave out (``_step`` False: its episode is over) is not
        planned for; its action is zeros, which the env does not take."""
        flat = tensordict.reshape(-1)
        if len(self._per_env) != flat.shape[0]:
            self._per_env = [self._for_env(i) for i in range(flat.shape[0])]
        step = flat.get(keys.PARTIAL_STEP, None)
        active = [True] * flat.shape[0] if step is None else step.reshape(-1).tolist()
        planned = {i: p(flat[i])[keys.ACTION] for i, p in enumerate(self._per_env) if active[i]}
        idle = torch.zeros_like(next(iter(planned.values())))
        actions = [planned.get(i, idle) for i in range(flat.shape[0])]
        action = torch.stack(actions).reshape(*tensordict.batch_size, -1)  # (*B, nu)
        tensordict.set(keys.ACTION, action)
        return tensordict

    @property
    def objective_factory(self) -> ObjectiveFactory:
        """What the planner plans on (set to any factory or plain callable: adapted by
        `as_objective_factory`)."""
        return self._objective_factory

    @objective_factory.setter
    def objective_factory(self, factory: ObjectiveFactory | Callable[..., Any]) -> None:
        self._objective_factory = as_objective_factory(factory)

    def _for_env(self, i: int) -> PlannerPolicy:
        """The policy of env i of a batch: this one's planner and objective, seed + i."""
        return PlannerPolicy(
            self.planner,
            self.objective_factory,
            self.replan_every,
            seed=self.seed + i,
            device=self.plan_device,
            action_dtype=self.action_dtype,
        )

    # ---------------------------------------------------------------- checkpointing
    def get_extra_state(self) -> dict[str, Any]:
        plan = None if self._plan is None else self._plan.clone()
        return {
            "plan": plan,
            "steps_since_plan": self._steps_since_plan,
            "episode_step": self._episode_step,
            "generator_state": self.generator.get_state().clone(),
            "carried": {k: v.clone() for k, v in self._carried.items()},
            "per_env": [policy.get_extra_state() for policy in self._per_env],
        }

    def set_extra_state(self, state: dict[str, Any]) -> None:
        plan = state["plan"]
        self._plan = None if plan is None else plan.to(self.plan_device).clone()
        self._steps_since_plan = int(state["steps_since_plan"])
        self._episode_step = int(state.get("episode_step", 0))
        self.generator.set_state(state["generator_state"].cpu())
        self._carried = {k: v.to(self.plan_device) for k, v in state.get("carried", {}).items()}
        self.last_result = None
        per_env = state.get("per_env", [])
        self._per_env = [self._for_env(i) for i in range(len(per_env))]
        for policy, env_state in zip(self._per_env, per_env, strict=True):
            policy.set_extra_state(env_state)
