"""`python -m mbrl_delan.fit [data=cmu_mocap|arrays] [model=delan|mlp|ensemble]`: inverse dynamics.

Learn ``(q, qd, qdd) -> tau`` from CMU motion capture retargeted onto a humanoid (the paper's
experiment, ``data=cmu_mocap``) or from your own robot's logged arrays (``data=arrays
data.path=FILE``, `mbrl_delan.data.arrays`), with DeLaN or a feed-forward network. The config
tree is ``mbrl_delan/configs/fit`` (``model=`` names an inverse-dynamics model of
`mbrl_delan.models.inverse` here). From Python: `fit_inverse_dynamics`.

Builds the dataset, trains the model on its training part (stages of falling learning rate
and early stopping on a validation split where the data config says so) and evaluates it on
every split. The run dir (``runs/fit/...``) receives ``config.yaml``,
``dataset_provenance.json``, ``metrics.jsonl`` (one record per epoch), ``summary.json``
(final errors per split, DoF group and clip or trajectory; DeLaN's positive-definiteness
check), ``model.pt`` and ``loss_curves.png``. Compare runs with ``python -m
mbrl_delan.fit_report``; evaluate a run on other data with ``python -m mbrl_delan.evaluate``.

Exit codes: 0 done, 2 bad config value, missing or malformed data file, missing clip or
dataset, 1 bad mocap data (NaN, malformed AMC, unstable PD tracking) or diverged training.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import NoReturn

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from mbrl_delan.conf.checks import (
    ConfigError,
    exit_on_config_errors,
    refuse_used_run_dir,
)
from mbrl_delan.data.arrays import ArrayFormatError
from mbrl_delan.data.buffer import NonFiniteDataError
from mbrl_delan.data.mocap import (
    ClipNotFoundError,
    ClipTooShortError,
    MocapFormatError,
    TrackingUnstableError,
)
from mbrl_delan.fit_run import (  # the fit's engine; its Python API re-exported here
    RUN_FILES,
    FitResult,
    fit_inverse_dynamics,
    run,
)
from mbrl_delan.runs import load_fit_model
from mbrl_delan.stops import stop
from mbrl_delan.sweep import discard_unstarted_run_dir
from mbrl_delan.systems.external import MissingPackageError
from mbrl_delan.training.fit import TrainingDivergedError

__all__ = ["FitResult", "fit_inverse_dynamics", "load_fit_model", "main"]

log = logging.getLogger(__name__)


def _exit_on_input(kind: str, err: Exception, run_dir: Path) -> NoReturn:
    """A bad input: one line (`kind`: what is wrong, the error), no run folder left, exit 2."""
    discard_unstarted_run_dir(run_dir, "fit.log")
    stop(kind, err)


@hydra.main(version_base="1.3", config_path="configs/fit", config_name="config")
def hydra_main(cfg: DictConfig) -> float | None:
    run_dir = Path(HydraConfig.get().runtime.output_dir)
    try:
        refuse_used_run_dir(run_dir, RUN_FILES, "start the new fit in another hydra.run.dir")
        summary = run(cfg, run_dir)
    except ConfigError as err:
        _exit_on_input("config error", err, run_dir)
    except (ClipNotFoundError, FileNotFoundError) as err:
        _exit_on_input("data not found", err, run_dir)
    except ArrayFormatError as err:
        _exit_on_input("bad data file", err, run_dir)
    except (NonFiniteDataError, MocapFormatError, ClipTooShortError, TrackingUnstableError) as err:
        _exit_on_input("bad data", err, run_dir)
    except MissingPackageError as err:
        _exit_on_input("missing package", err, run_dir)
    except TrainingDivergedError as err:
        stop("training diverged", err, 1)
    return summary.get("val_clip_mse")


def main() -> None:
    """``python -m mbrl_delan.fit``: a config error, Hydra's included, exits 2 naming it."""
    exit_on_config_errors(hydra_main)


if __name__ == "__main__":
    main()
