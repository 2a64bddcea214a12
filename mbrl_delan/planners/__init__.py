"""Sampling planners (CEM, iCEM, MPPI, predictive sampling) over an objective, optionally
over spline knots, and their TorchRL policy wrapper.

The objectives they optimise (the learned model's, MuJoCo's) are in `mbrl_delan.objectives`.
"""

from mbrl_delan.planners.base import (
    PlanResult,
    SamplingDistribution,
    SamplingPlanner,
    SamplingSettings,
)
from mbrl_delan.planners.cem import CEMPlanner, CEMSettings
from mbrl_delan.planners.icem import ICEMPlanner, ICEMPlanResult, ICEMSettings, colored_noise
from mbrl_delan.planners.mppi import MPPIPlanner, MPPISettings, mppi_weights
from mbrl_delan.planners.policy import PlannerPolicy
from mbrl_delan.planners.predictive import PredictiveSampling, PredictiveSettings
from mbrl_delan.planners.spline import INTERPOLATIONS, KnotSpline

__all__ = [
    "INTERPOLATIONS",
    "CEMPlanner",
    "CEMSettings",
    "ICEMPlanResult",
    "ICEMPlanner",
    "ICEMSettings",
    "MPPIPlanner",
    "MPPISettings",
    "PlanResult",
    "PlannerPolicy",
    "PredictiveSampling",
    "PredictiveSettings",
    "KnotSpline",
    "SamplingDistribution",
    "SamplingPlanner",
    "SamplingSettings",
    "colored_noise",
    "mppi_weights",
]
