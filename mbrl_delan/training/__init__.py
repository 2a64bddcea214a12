"""Fitting world models, checkpoints and run records.

Plotting lives in ``mbrl_delan.training.plots`` (imported on demand: it loads matplotlib).
"""

from mbrl_delan.training.checkpoint import (
    CheckpointError,
    load_checkpoint,
    rng_state,
    save_checkpoint,
    set_rng_state,
)
from mbrl_delan.training.fit import FitConfig, FitReport, TrainingDivergedError, fit_model
from mbrl_delan.training.recorder import Recorder, read_metrics

__all__ = [
    "CheckpointError",
    "FitConfig",
    "FitReport",
    "Recorder",
    "TrainingDivergedError",
    "fit_model",
    "load_checkpoint",
    "read_metrics",
    "rng_state",
    "save_checkpoint",
    "set_rng_state",
]
