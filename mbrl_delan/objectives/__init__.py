"""Objectives: what a planner optimises, the returns of action sequences from one state.

- `base`: the `Objective` / `ObjectiveFactory` protocol, `discounted_masked_return`,
  `risk_adjusted_return`.
- `model`: the learned-model objective (`model_objective_factory`), run through the
  acceleration layer (`mbrl_delan.accelerate`).
- `mujoco`: MuJoCo's true dynamics (`mujoco_objective_factory`), the oracle.
"""

from mbrl_delan.objectives.base import (
    Objective,
    ObjectiveFactory,
    discounted_masked_return,
    risk_adjusted_return,
)
from mbrl_delan.objectives.model import ModelObjectiveFactory, model_objective_factory
from mbrl_delan.objectives.mujoco import MujocoObjectiveFactory, mujoco_objective_factory

__all__ = [
    "ModelObjectiveFactory",
    "MujocoObjectiveFactory",
    "Objective",
    "ObjectiveFactory",
    "discounted_masked_return",
    "mujoco_objective_factory",
    "model_objective_factory",
    "risk_adjusted_return",
]
