"""Sampling planners (CEM, iCEM, MPPI) over an objective, and their TorchRL policy wrapper.

The objectives they optimise (the learned model's, MuJoCo's) are in `mbrl_delan.objectives`.
"""

from mbrl_delan.planners.base import PlanResult, SamplingDistribution, SamplingPlanner
from mbrl_delan.planners.cem import CEMPlanner
from mbrl_delan.planners.icem import ICEMPlanner, ICEMPlanResult, colored_noise
from mbrl_delan.planners.mppi import MPPIPlanner, mppi_weights
from mbrl_delan.planners.policy import PlannerPolicy

__all__ = [
    "CEMPlanner",
    "ICEMPlanResult",
    "ICEMPlanner",
    "MPPIPlanner",
    "PlanResult",
    "PlannerPolicy",
    "SamplingDistribution",
    "SamplingPlanner",
    "colored_noise",
    "mppi_weights",
]
