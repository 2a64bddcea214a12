"""A world model and a task as TorchRL modules: TorchRL's `WorldModelWrapper` of the model's
one-step transition (a `TensorDictModule`) and the task's reward, the module `ModelEnv` steps.

    wrapper = world_model_wrapper(model, task, system)   # DeLaN, the ensemble, any WorldModel
    td = wrapper(TensorDict({"q": q, "qd": qd, "action": u}, batch_size=[N]))
    td["q"], td["qd"], td["reward"], td["terminated"]    # the next state and its reward

The loop plans through its own fused objective (`objectives.model.model_objective_factory`,
compiled and CUDA-graphed where asked); these modules are the same step for TorchRL's
machinery (`ModelEnv`, its planners, collectors and losses).
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase
from torch import Tensor, nn
from torchrl.modules import WorldModelWrapper

from mbrl_delan import keys
from mbrl_delan.models.base import WorldModel, eval_mode, model_placement
from mbrl_delan.systems.system import System
from mbrl_delan.tasks.base import Task


class Transition(nn.Module):
    """A WorldModel's `step` as a network: (q, qd, action) -> the next (q, qd), with the
    controls clamped to the system's range, the model in eval mode, the state in `dtype` on
    `device`. Random models (ensembles) draw from `generator`."""

    def __init__(
        self,
        model: WorldModel,
        system: System,
        device: torch.device,
        dtype: torch.dtype,
        generator: torch.Generator | None = None,
    ) -> None:
        super().__init__()
        self.model = model
        self.register_buffer("ctrl_low", system.ctrl_low.clone(), persistent=False)  # (nu,)
        self.register_buffer("ctrl_high", system.ctrl_high.clone(), persistent=False)
        self.device, self.dtype, self.generator = device, dtype, generator

    def forward(self, q: Tensor, qd: Tensor, action: Tensor) -> tuple[Tensor, Tensor]:
        """(*B, nq), (*B, nv), (*B, nu) -> next q (*B, nq), next qd (*B, nv)."""
        action = torch.clamp(action, self.ctrl_low.to(action), self.ctrl_high.to(action))
        with eval_mode(self.model):
            nxt = self.model.step(q, qd, action, generator=self.generator)
        return nxt.q.to(self.device, self.dtype), nxt.qd.to(self.device, self.dtype)


class TaskReward(TensorDictModuleBase):
    """The task's reward and termination of the reached state: reads q, qd (the transition's
    output), the action and, for a time-indexed task, TorchRL's ``step_count``; writes reward
    (*B, 1), done, terminated and truncated (*B, 1) (truncation is a `StepCounter`'s)."""

    def __init__(self, task: Task, dtype: torch.dtype) -> None:
        super().__init__()
        self.task, self.dtype = task, dtype
        self.in_keys = [keys.Q, keys.QD, keys.ACTION]
        self.out_keys = [keys.REWARD, keys.DONE, keys.TERMINATED, keys.TRUNCATED]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        q, qd = tensordict.get(keys.Q), tensordict.get(keys.QD)
        action = tensordict.get(keys.ACTION)
        step = self.episode_step(tensordict, q.device)  # (*B,) or ()
        reward = self.task.reward_at(q, qd, action, step).to(self.dtype).unsqueeze(-1)
        terminated = self.task.terminated_at(q, qd, step).to(q.device, torch.bool).unsqueeze(-1)
        tensordict.set(keys.REWARD, reward)
        tensordict.set(keys.DONE, terminated.clone())
        tensordict.set(keys.TERMINATED, terminated)
        tensordict.set(keys.TRUNCATED, torch.zeros_like(terminated))
        return tensordict

    def episode_step(self, tensordict: TensorDictBase, device: torch.device) -> Tensor:
        """The episode step of the action, from ``step_count`` (*B, 1); 0 for a task without
        time. A time-indexed task without it is a ValueError naming the transform to add."""
        count = tensordict.get(keys.STEP_COUNT, None)
        if count is not None:
            return count.squeeze(-1)
        if self.task.time_indexed:
            raise ValueError(
                f"task {self.task.name!r} is time-indexed: the model env needs the episode step "
                f"in {keys.STEP_COUNT!r}; append torchrl.envs.StepCounter() to the env"
            )
        return torch.zeros((), dtype=torch.long, device=device)


class ReturnToGo(nn.Module):
    """An advantage module for TorchRL's `MPPIPlanner`: each candidate's undiscounted sum of
    rewards from each step on, less the best candidate's return, written to ``advantage``
    (..., N, H, 1); MPPI reads its first step, R_k - max_j R_j <= 0.

    TorchRL's MPPI weighs candidate k by exp(temperature * advantage_k) with no maximum taken
    out: on raw returns the weights overflow to inf (NaN actions) once temperature x return
    passes about 88 in float32. The shift leaves the weights' ratios, the top-k and the plan
    as they were (a softmax does not change under a common shift) and keeps every weight in
    (0, 1], the best candidate's at 1.
    """

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        reward = tensordict.get(keys.NEXT_REWARD)  # (..., N, H, 1), post-done rewards zeroed
        to_go = reward.flip(-2).cumsum(-2).flip(-2)  # (..., N, H, 1)
        best = to_go[..., :1, :].amax(dim=-3, keepdim=True)  # (..., 1, 1, 1)
        tensordict.set("advantage", to_go - best)
        return tensordict


def world_model_wrapper(
    model: WorldModel,
    task: Task,
    system: System,
    device: torch.device | str | None = None,
    dtype: torch.dtype | None = None,
    generator: torch.Generator | None = None,
) -> WorldModelWrapper:
    """TorchRL's `WorldModelWrapper` of `model`'s transition (a `TensorDictModule` from q, qd,
    action to the next q, qd) and `task`'s reward (`TaskReward`); the state in `dtype` on
    `device` (default: the model's)."""
    place = model_placement(model, fallback_device=device or "cpu")
    device = torch.device(device) if device is not None else place.device
    transition = Transition(model, system, device, dtype or place.dtype, generator)
    return WorldModelWrapper(
        TensorDictModule(
            transition, in_keys=[keys.Q, keys.QD, keys.ACTION], out_keys=[keys.Q, keys.QD]
        ),
        TaskReward(task, dtype or place.dtype),
    )
