"""Sampling planners (CEM, iCEM, MPPI), their TorchRL policy wrapper and the oracle."""

from mbrl_delan.planners.base import (
    Objective,
    ObjectiveFactory,
    PlanResult,
    SamplingDistribution,
    SamplingPlanner,
    risk_adjusted_return,
)
from mbrl_delan.planners.cem import CEMPlanner
from mbrl_delan.planners.icem import ICEMPlanner, ICEMPlanResult, colored_noise
from mbrl_delan.planners.mppi import MPPIPlanner, mppi_weights
from mbrl_delan.planners.oracle import (
    MujocoObjective,
    MujocoObjectiveFactory,
    mujoco_objective_factory,
)
from mbrl_delan.planners.policy import PlannerPolicy

__all__ = [
    "CEMPlanner",
    "ICEMPlanResult",
    "ICEMPlanner",
    "MPPIPlanner",
    "MujocoObjective",
    "MujocoObjectiveFactory",
    "Objective",
    "ObjectiveFactory",
    "PlanResult",
    "PlannerPolicy",
    "SamplingDistribution",
    "SamplingPlanner",
    "colored_noise",
    "mppi_weights",
    "mujoco_objective_factory",
    "risk_adjusted_return",
]
