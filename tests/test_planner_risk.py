"""The risk setting: score = mean - risk * std over particles, on a worked example."""

from __future__ import annotations

import pytest
import torch
from hydra import compose, initialize_config_dir
from tensordict import TensorDictBase
from torch import Tensor

from mbrl_delan.conf.checks import CONFIG_DIR, ConfigError, validate_train_config
from mbrl_delan.models.base import LossOutput, WorldModel
from mbrl_delan.objectives.base import risk_adjusted_return
from mbrl_delan.objectives.model import model_objective_factory
from mbrl_delan.planners import CEMPlanner
from mbrl_delan.systems.system import State
from mbrl_delan.tasks.base import Task

CONFIGS = CONFIG_DIR


class TwoMembers(WorldModel):
    """q' = q + gain_e a + offset_e for member e = b % 2 of a flat batch (TSinf-like)."""

    def __init__(self, gains: tuple[float, float], offsets: tuple[float, float]) -> None:
        super().__init__()
        self.register_buffer("gains", torch.tensor(gains, dtype=torch.float64))
        self.register_buffer("offsets", torch.tensor(offsets, dtype=torch.float64))

    def step(
        self, q: Tensor, qd: Tensor, action: Tensor, generator: torch.Generator | None = None
    ) -> State:
        member = torch.arange(q.shape[0], device=q.device) % 2  # (B,)
        gain, offset = self.gains[member, None], self.offsets[member, None]  # (B, 1)
        return State(q=q + gain * action + offset, qd=qd)

    def loss(self, batch: TensorDictBase) -> LossOutput:
        raise NotImplementedError


class HeightTask(Task):
    """r = q (the reached position)."""

    name = "height"
    episode_len = 1

    def reward(self, q: Tensor, qd: Tensor, action: Tensor) -> Tensor:
        return q[..., 0]

    def initial_state(self, batch_shape: tuple[int, ...], generator: torch.Generator) -> State:
        raise NotImplementedError


# The worked example, H = 1, from q = 0, member gains (0, 3) and offsets (1, 1):
#   sequence A, a = 0: particle returns (1, 1), mean 1.0, std 0.0
#   sequence B, a = 1: particle returns (1, 4), mean 2.5, std 1.5 (divisor P = 2)
# risk 0: scores (1.0, 2.5), B wins; risk 2: scores (1.0, 2.5 - 3.0 = -0.5), A wins.
ACTIONS = torch.tensor([[[0.0]], [[1.0]]], dtype=torch.float64)  # (N=2, H=1, nu=1)
PARTICLE_RETURNS = torch.tensor([[1.0, 1.0], [1.0, 4.0]], dtype=torch.float64)  # (N, P)


def objective(risk: float):
    factory = model_objective_factory(
        TwoMembers(gains=(0.0, 3.0), offsets=(1.0, 1.0)), HeightTask(), particles=2, risk=risk
    )
    zero = torch.zeros(1, dtype=torch.float64)
    return factory(zero, zero)


@pytest.mark.parametrize(
    ("risk", "scores", "winner"), [(0.0, (1.0, 2.5), 1), (2.0, (1.0, -0.5), 0)]
)
def test_worked_example(risk: float, scores: tuple[float, float], winner: int) -> None:
    expected = torch.tensor(scores, dtype=torch.float64)
    torch.testing.assert_close(risk_adjusted_return(PARTICLE_RETURNS, risk), expected)
    returns = objective(risk)(ACTIONS)  # the same numbers through the model objective
    torch.testing.assert_close(returns, expected)
    assert int(returns.argmax()) == winner


def test_planner_follows_the_risk() -> None:
    """On a in [0, 1] the score is 1 + 1.5 a - 1.5 risk |a|: optimum a = 1 at risk 0, a = 0
    at risk 2."""
    planner = CEMPlanner(
        1,
        [0.0],
        [1.0],
        num_samples=64,
        num_elites=8,
        iterations=8,
        init_std=1.0,
        dtype=torch.float64,
    )
    for risk, optimum in ((0.0, 1.0), (2.0, 0.0)):
        result = planner.plan(objective(risk), None, torch.Generator().manual_seed(0))
        assert abs(result.first_action.item() - optimum) < 0.05, (risk, result.first_action)


def test_one_particle_ignores_risk() -> None:
    returns = torch.tensor([[3.0], [-1.0]])
    torch.testing.assert_close(risk_adjusted_return(returns, 5.0), torch.tensor([3.0, -1.0]))
    with pytest.raises(ValueError, match="particle_returns"):
        risk_adjusted_return(torch.zeros(3), 1.0)
    with pytest.raises(ValueError, match="risk"):
        model_objective_factory(TwoMembers((0.0, 0.0), (0.0, 0.0)), HeightTask(), risk=float("nan"))


@pytest.mark.parametrize("planner", ["cem", "icem", "mppi"])
def test_every_planner_config_has_risk_zero(planner: str) -> None:
    with initialize_config_dir(str(CONFIGS), version_base="1.3"):
        cfg = compose("config", overrides=[f"planner={planner}"])
        assert cfg.planner.risk == 0.0
        validate_train_config(cfg)
        bad = compose("config", overrides=[f"planner={planner}", "planner.risk=nan"])
    with pytest.raises(ConfigError, match="planner.risk"):
        validate_train_config(bad)
