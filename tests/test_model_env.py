"""Model objective and ModelEnv on a toy world model with hand-computed returns."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDictBase
from torch import Tensor, nn
from torchrl.envs.utils import check_env_specs

from mbrl_delan import keys
from mbrl_delan.envs.model_env import ModelEnv
from mbrl_delan.models.base import LossOutput, WorldModel
from mbrl_delan.objectives.model import model_objective_factory
from mbrl_delan.planners import CEMPlanner, MPPIPlanner
from mbrl_delan.systems.system import State, load_system
from mbrl_delan.tasks.base import Task

DT = 0.1


class DoubleIntegrator(WorldModel):
    """q' = q + dt qd, qd' = qd + dt a (+ offset[b % E] on q' for member b % E of a flat batch)."""

    def __init__(self, offsets: tuple[float, ...] = (0.0,), dtype: torch.dtype = torch.float64):
        super().__init__()
        self.register_buffer("offsets", torch.tensor(offsets, dtype=dtype))

    def step(
        self, q: Tensor, qd: Tensor, action: Tensor, generator: torch.Generator | None = None
    ) -> State:
        batch = q.shape[:-1]
        flat = torch.arange(batch.numel(), device=q.device).reshape(batch)
        offset = self.offsets[flat % self.offsets.numel()].unsqueeze(-1)  # (..., 1)
        return State(q=q + DT * qd + offset, qd=qd + DT * action)

    def loss(self, batch: TensorDictBase) -> LossOutput:
        raise NotImplementedError


class QuadraticTask(Task):
    """r = -|q|^2 - 0.1 |a|^2, terminated when q_0 > 2."""

    name = "quadratic"
    episode_len = 20

    def reward(self, q: Tensor, qd: Tensor, action: Tensor) -> Tensor:
        return -q.square().sum(-1) - 0.1 * action.square().sum(-1)

    def terminated(self, q: Tensor, qd: Tensor) -> Tensor:
        return q[..., 0] > 2.0

    def initial_state(self, batch_shape: tuple[int, ...], generator: torch.Generator) -> State:
        shape = (*batch_shape, 1)
        q = torch.rand(shape, generator=generator, dtype=torch.float64, device=generator.device)
        return State(q=q - 0.5, qd=torch.zeros(shape, dtype=torch.float64, device=generator.device))


class EndlessQuadraticTask(QuadraticTask):
    """QuadraticTask without termination (ending early would pay with negative rewards)."""

    def terminated(self, q: Tensor, qd: Tensor) -> Tensor:
        return torch.zeros(q.shape[:-1], dtype=torch.bool, device=q.device)


def one(x: float, dtype: torch.dtype = torch.float64) -> Tensor:
    return torch.tensor([x], dtype=dtype)


def test_model_objective_hand_computed() -> None:
    objective = model_objective_factory(DoubleIntegrator(), QuadraticTask())(one(0.0), one(0.0))
    actions = torch.ones(1, 3, 1, dtype=torch.float64)
    # q: 0, 0.01, 0.03; qd: 0.1, 0.2, 0.3; each step costs 0.1 for the action
    expected = -(0.0 + 0.1) - (0.01**2 + 0.1) - (0.03**2 + 0.1)
    assert objective(actions).item() == pytest.approx(expected, abs=1e-12)


def test_model_objective_discount_and_batch() -> None:
    factory = model_objective_factory(DoubleIntegrator(), QuadraticTask(), discount=0.5)
    actions = torch.stack([torch.ones(3, 1), torch.zeros(3, 1)]).double()  # (2, 3, 1)
    returns = factory(one(0.0), one(0.0))(actions)
    expected = -0.1 - 0.5 * (0.01**2 + 0.1) - 0.25 * (0.03**2 + 0.1)
    assert returns.shape == (2,)
    assert returns[0].item() == pytest.approx(expected, abs=1e-12)
    assert returns[1].item() == 0.0


def test_model_objective_done_masking() -> None:
    factory = model_objective_factory(DoubleIntegrator(), QuadraticTask())
    # q1 = 1.95 + 0.1 = 2.05 terminates at the first step: only that reward counts
    returns = factory(one(1.95), one(1.0))(torch.zeros(1, 3, 1, dtype=torch.float64))
    assert returns.item() == pytest.approx(-(2.05**2), abs=1e-12)


def test_model_objective_particles_mean_over_members() -> None:
    """With P = E = 2 every sample sees both members, whatever N is (index n * P + p)."""
    offsets = (0.0, 1.0)
    model = DoubleIntegrator(offsets)
    factory = model_objective_factory(model, QuadraticTask(), particles=2)
    actions = torch.zeros(3, 1, 1, dtype=torch.float64)  # N = 3 (odd), H = 1
    returns = factory(one(0.0), one(0.0))(actions)
    expected = -(0.0**2 + 1.0**2) / 2
    torch.testing.assert_close(returns, torch.full((3,), expected, dtype=torch.float64))


def test_model_objective_casts_to_model_dtype() -> None:
    model = DoubleIntegrator(dtype=torch.float64)
    objective = model_objective_factory(model, QuadraticTask())(
        one(0.0, torch.float32), one(0.0, torch.float32)
    )
    returns = objective(torch.ones(2, 3, 1, dtype=torch.float32))
    assert returns.dtype == torch.float32
    assert returns[0].item() == pytest.approx(-0.3010, abs=1e-6)


def test_model_objective_restores_training_mode() -> None:
    model = DoubleIntegrator()
    model.train()
    seen = []
    original = model.step

    def step(*args: Tensor, **kwargs: object) -> State:
        seen.append(model.training)
        return original(*args, **kwargs)

    model.step = step  # type: ignore[method-assign]
    model_objective_factory(model, QuadraticTask())(one(0.0), one(0.0))(torch.zeros(1, 2, 1))
    assert seen == [False, False] and model.training


@pytest.mark.parametrize("planner_cls", [CEMPlanner, MPPIPlanner])
def test_planner_on_toy_model_brakes(planner_cls: type) -> None:
    """From q = 1, moving away at qd = 1, the first action must push back (negative)."""
    kwargs = {"num_elites": 20} if planner_cls is CEMPlanner else {"temperature": 0.1}
    planner = planner_cls(
        10, [-1.0], [1.0], num_samples=200, iterations=5, dtype=torch.float64, **kwargs
    )
    task = EndlessQuadraticTask()
    objective = model_objective_factory(DoubleIntegrator(), task)(one(1.0), one(1.0))
    result = planner.plan(objective, None, torch.Generator().manual_seed(0))
    assert result.first_action.item() < -0.5


def test_model_env_check_env_specs() -> None:
    system = load_system("pendulum", frame_skip=5)
    env = ModelEnv(DoubleIntegrator(), QuadraticTask(), system, seed=0)
    check_env_specs(env)
    td = env.rollout(5)
    for key in (
        keys.Q,
        keys.QD,
        keys.ACTION,
        keys.NEXT_REWARD,
        keys.NEXT_DONE,
        keys.NEXT_TERMINATED,
        keys.NEXT_TRUNCATED,
    ):
        assert key in td.keys(include_nested=True), key
    assert td[keys.NEXT_Q].dtype == torch.float64
    # the step is the toy model's
    torch.testing.assert_close(td[keys.NEXT_Q], td[keys.Q] + DT * td[keys.QD])


def test_model_env_batched_and_terminates() -> None:
    system = load_system("pendulum", frame_skip=5)
    env = ModelEnv(
        DoubleIntegrator(dtype=torch.float32), QuadraticTask(), system, batch_size=(4,), seed=1
    )
    check_env_specs(env)
    td = env.reset()
    assert td[keys.Q].shape == (4, 1) and td[keys.Q].dtype == torch.float32
    td[keys.Q] = torch.full((4, 1), 1.95)
    td[keys.QD] = torch.ones(4, 1)
    td[keys.ACTION] = torch.zeros(4, 1)
    out = env.step(td)
    assert bool(out[keys.NEXT_TERMINATED].all()) and bool(out[keys.NEXT_DONE].all())
    assert not bool(out[keys.NEXT_TRUNCATED].any())


def test_model_env_seed_reproducible() -> None:
    system = load_system("pendulum", frame_skip=5)
    env = ModelEnv(DoubleIntegrator(), QuadraticTask(), system)
    env.set_seed(3)
    first = env.reset()[keys.Q]
    env.set_seed(3)
    torch.testing.assert_close(env.reset()[keys.Q], first)


def test_model_placement_without_parameters_is_float64() -> None:
    class Bare(DoubleIntegrator):
        def __init__(self) -> None:
            nn.Module.__init__(self)
            self.offsets = torch.zeros(1)  # plain attribute, not a buffer

    objective = model_objective_factory(Bare(), QuadraticTask())(
        one(0.0, torch.float32), one(0.0, torch.float32)
    )
    assert objective(torch.ones(1, 3, 1)).item() == pytest.approx(-0.301, abs=1e-6)


def test_model_env_partial_reset_keeps_other_envs() -> None:
    system = load_system("pendulum", frame_skip=5)
    env = ModelEnv(DoubleIntegrator(), QuadraticTask(), system, batch_size=(4,), seed=1)
    td = env.reset()
    td[keys.Q] = torch.full((4, 1), 9.0, dtype=torch.float64)
    td[env.reset_keys[0]] = torch.tensor([[True], [False], [True], [False]])
    q = env.reset(td)[keys.Q][:, 0]
    assert (q[[1, 3]] == 9.0).all() and (q[[0, 2]].abs() <= 0.5).all()


def test_torchrl_planner_runs_through_terminations() -> None:
    """The env is not batch-locked: TorchRL's planners expand the start state to
    (num_candidates,) and reset the candidates that terminate mid-rollout; the reset must
    give states for that whole batch."""
    from torchrl.modules.planners import CEMPlanner as TorchRLCEMPlanner

    env = ModelEnv(DoubleIntegrator(), QuadraticTask(), load_system("pendulum"), seed=0)
    start = env.reset()
    start[keys.Q] = torch.full((1,), 1.95, dtype=torch.float64)  # q > 2 after one step
    start[keys.QD] = torch.ones(1, dtype=torch.float64)
    planner = TorchRLCEMPlanner(env, planning_horizon=3, optim_steps=1, num_candidates=8, top_k=2)
    action = planner(start.clone())[keys.ACTION]
    assert action.shape == (1,) and torch.isfinite(action).all()
