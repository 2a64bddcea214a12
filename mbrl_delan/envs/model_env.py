"""`ModelEnv`: a TorchRL `ModelBasedEnvBase` around a WorldModel and a Task (imagination
inside a learned world model, for TorchRL's own planners and collectors)."""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from torch import Tensor
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs.model_based import ModelBasedEnvBase

from mbrl_delan import keys
from mbrl_delan.models.base import WorldModel, eval_mode, model_placement
from mbrl_delan.systems.system import System
from mbrl_delan.tasks.base import Task


class ModelEnv(ModelBasedEnvBase):
    """A TorchRL env that steps a WorldModel and scores it with a Task.

    Keys: q, qd (observations), action, reward, done, terminated, truncated. `reset` draws
    `task.initial_state`; truncation is never set here (add a `StepCounter` transform with
    `max_steps=task.episode_len` for episode limits). The model runs in eval mode and on its
    own device; the env's dtype is the model's unless given. A time-indexed task reads the
    episode step from TorchRL's `step_count` key, so it needs the `StepCounter` transform.
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
        super().__init__(model, device=device, batch_size=torch.Size(batch_size))
        self.task = task
        self.system = system
        self.state_dtype = dtype or place.dtype
        self._generator = torch.Generator(device=self.device)
        self._generator.manual_seed(seed)
        self._make_specs()

    def _make_specs(self) -> None:
        bs, dt, sys = self.batch_size, self.state_dtype, self.system
        self.observation_spec = Composite(
            {
                keys.Q: Unbounded((*bs, sys.nq), dtype=dt, device=self.device),
                keys.QD: Unbounded((*bs, sys.nv), dtype=dt, device=self.device),
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
        return TensorDict(
            {keys.Q: q, keys.QD: qd, **self._flags(not_done)}, batch_size=batch, device=self.device
        )

    def _step(self, tensordict: TensorDictBase) -> TensorDict:
        q, qd = tensordict.get(keys.Q), tensordict.get(keys.QD)
        action = tensordict.get(keys.ACTION)
        low, high = self.system.ctrl_low, self.system.ctrl_high
        action = torch.clamp(action, low.to(action), high.to(action))
        with eval_mode(self.world_model):
            nxt = self.world_model.step(q, qd, action, generator=self._generator)
        q1 = nxt.q.to(self.device, self.state_dtype)
        qd1 = nxt.qd.to(self.device, self.state_dtype)
        step = self._episode_step(tensordict)  # (*B,) or () for tasks without time
        reward = self.task.reward_at(q1, qd1, action, step).to(self.state_dtype).unsqueeze(-1)
        terminated = self.task.terminated_at(q1, qd1, step)
        return TensorDict(
            {keys.Q: q1, keys.QD: qd1, keys.REWARD: reward, **self._flags(terminated)},
            batch_size=tensordict.batch_size,
            device=self.device,
        )

    def _episode_step(self, tensordict: TensorDictBase) -> Tensor:
        """The episode step of the action, from `step_count` (*B, 1); 0 for tasks without time."""
        count = tensordict.get(keys.STEP_COUNT, None)
        if count is not None:
            return count.squeeze(-1)
        if self.task.time_indexed:
            raise ValueError(
                f"task {self.task.name!r} is time-indexed: ModelEnv needs the episode step in "
                f"{keys.STEP_COUNT!r}; append torchrl.envs.StepCounter() to the env"
            )
        return torch.zeros((), dtype=torch.long, device=self.device)

    def _set_seed(self, seed: int | None) -> None:
        if seed is not None:
            self._generator.manual_seed(seed)
