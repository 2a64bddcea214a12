"""`ModelEnv`: a TorchRL `ModelBasedEnvBase` that steps a WorldModel and a Task as TorchRL's
`WorldModelWrapper` (`envs.modules.world_model_wrapper`): imagination inside a learned world
model, for TorchRL's own planners and collectors."""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from torch import Tensor
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs.model_based import ModelBasedEnvBase

from mbrl_delan import keys
from mbrl_delan.envs.modules import world_model_wrapper
from mbrl_delan.models.base import WorldModel, model_placement
from mbrl_delan.systems.system import System
from mbrl_delan.tasks.base import Task


class ModelEnv(ModelBasedEnvBase):
    """A TorchRL env that steps a WorldModel and scores it with a Task.

    Keys: q, qd, step_count (observations), action, reward, done, terminated, truncated.
    `reset` draws `task.initial_state` at step 0; `step` runs `world_model` (TorchRL's
    `WorldModelWrapper` of the model's transition and the task's reward, which a time-indexed
    task reads the step of) and counts the step. Truncation is never set here: a
    `StepCounter(max_steps=task.episode_len)` transform adds episode limits (it counts in the
    same key). A rollout may start from a state without a step count (a real env's, for
    TorchRL's planners): step 0 then, or a ValueError for a time-indexed task. The model runs
    in eval mode and on its own device; the env's dtype is the model's unless given.
    """

    def __init__(
        self,
        model: WorldModel,
        task: Task,
        system: System,
        batch_size: tuple[int, ...] | torch.Size = (),
        device: torch.device | str | None = None,
        dtype: torch.dtype | None = None,
        seed: int = 0,
    ) -> None:
        place = model_placement(model, fallback_device=device or "cpu")
        device = torch.device(device) if device is not None else place.device
        generator = torch.Generator(device=device)
        generator.manual_seed(seed)
        wrapper = world_model_wrapper(model, task, system, device, dtype or place.dtype, generator)
        super().__init__(wrapper, device=device, batch_size=torch.Size(batch_size))
        self.model = model
        self.task = task
        self.system = system
        self.state_dtype = dtype or place.dtype
        self._generator = generator
        self._make_specs()

    def _make_specs(self) -> None:
        bs, dt, sys = self.batch_size, self.state_dtype, self.system
        self.observation_spec = Composite(
            {
                keys.Q: Unbounded((*bs, sys.nq), dtype=dt, device=self.device),
                keys.QD: Unbounded((*bs, sys.nv), dtype=dt, device=self.device),
                keys.STEP_COUNT: Unbounded((*bs, 1), dtype=torch.long, device=self.device),
            },
            shape=bs,
            device=self.device,
        )
        low, high = sys.ctrl_low.to(dt), sys.ctrl_high.to(dt)
        if bool(torch.isfinite(low).all() and torch.isfinite(high).all()):
            self.action_spec = Bounded(
                low.expand(*bs, sys.nu),
                high.expand(*bs, sys.nu),
                shape=(*bs, sys.nu),
                dtype=dt,
                device=self.device,
            )
        else:
            self.action_spec = Unbounded((*bs, sys.nu), dtype=dt, device=self.device)
        self.reward_spec = Unbounded((*bs, 1), dtype=dt, device=self.device)
        flag = Categorical(2, shape=(*bs, 1), dtype=torch.bool, device=self.device)
        self.full_done_spec = Composite(
            {keys.DONE: flag.clone(), keys.TERMINATED: flag.clone(), keys.TRUNCATED: flag.clone()},
            shape=bs,
            device=self.device,
        )

    def _flags(self, terminated: Tensor) -> dict[str, Tensor]:
        """done / terminated / truncated entries from terminated (*B,) bool."""
        term = terminated.to(self.device, torch.bool).unsqueeze(-1)
        return {
            keys.DONE: term.clone(),
            keys.TERMINATED: term,
            keys.TRUNCATED: torch.zeros_like(term),
        }

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs: object) -> TensorDict:
        # the env is not batch-locked: a larger input batch (TorchRL's planners expand the
        # start state to (num_candidates,) and reset the finished ones) gets states for all
        batch = self.batch_size if tensordict is None else tensordict.batch_size
        state = self.task.initial_state(tuple(batch), self._generator)
        q = state.q.to(self.device, self.state_dtype)
        qd = state.qd.to(self.device, self.state_dtype)
        not_done = torch.zeros(q.shape[:-1], dtype=torch.bool, device=self.device)
        count = torch.zeros((*batch, 1), dtype=torch.long, device=self.device)
        return TensorDict(
            {keys.Q: q, keys.QD: qd, keys.STEP_COUNT: count, **self._flags(not_done)},
            batch_size=batch,
            device=self.device,
        )

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        count = tensordict.get(keys.STEP_COUNT, None)  # (*B, 1)
        if count is None:
            # a rollout started from a state without a step count (TorchRL's planners from a
            # real env without a StepCounter): step 0, for a task without time; set on the
            # input too, where a StepCounter on this env reads it
            self.world_model.get_reward_operator().episode_step(tensordict, self.device)
            count = torch.zeros((*tensordict.batch_size, 1), dtype=torch.long, device=self.device)
            tensordict.set(keys.STEP_COUNT, count)
        out = super()._step(tensordict)
        out.set(keys.STEP_COUNT, count + 1)
        return out

    def _set_seed(self, seed: int | None) -> None:
        if seed is not None:
            self._generator.manual_seed(seed)
