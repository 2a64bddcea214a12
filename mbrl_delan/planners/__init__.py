"""Sampling planners (CEM, iCEM, MPPI, predictive sampling) over an objective, optionally
over spline knots, and their TorchRL policy wrapper.

The objectives they optimise (the learned model's, MuJoCo's) are in `mbrl_delan.objectives`.
"""

from mbrl_delan.planners.base import PlanResult, SamplingDistribution, SamplingPlanner
from mbrl_delan.planners.cem import CEMPlanner
from mbrl_delan.planners.icem import ICEMPlanner, ICEMPlanResult, colored_noise
from mbrl_delan.planners.mppi import MPPIPlanner, mppi_weights
from mbrl_delan.planners.policy import PlannerPolicy
from mbrl_delan.planners.predictive import PredictiveSampling
from mbrl_delan.planners.spline import INTERPOLATIONS, KnotSpline

__all__ = [
    "INTERPOLATIONS",
    "CEMPlanner",
    "ICEMPlanResult",
    "ICEMPlanner",
    "MPPIPlanner",
    "PlanResult",
    "PlannerPolicy",
    "PredictiveSampling",
    "KnotSpline",
    "SamplingDistribution",
    "SamplingPlanner",
    "colored_noise",
    "mppi_weights",
]
