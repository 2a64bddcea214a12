"""Fitting an inverse-dynamics model on fixed splits, with every split's errors after each epoch.

`fit_inverse_model` runs epochs of shuffled minibatches on the training part and, after every
epoch, evaluates the model on each named split (``train``, ``val_time``, ``val_clip``) with
`evaluate_torques`: normalised MSE (the loss), MSE in SI units and R^2, per DoF and overall.
Without a stopping split the weights after the last epoch are kept; with one
(``InverseFitSettings.stop_on``) training ends after ``patience`` epochs without a lower error
on it and the weights of its lowest error are restored. A NaN/inf loss or gradient restores
the last completed epoch's weights and raises `TrainingDivergedError`.
"""

from __future__ import annotations

import logging
import math
import pickle
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDictBase
from torch import Tensor

from mbrl_delan import keys
from mbrl_delan.models.inverse import DeLaNInverse, InverseDynamicsModel
from mbrl_delan.training.fit import (
    Diverged,
    FitReport,
    TrainingDivergedError,
    batches,
    optimizer_epoch,
)
from mbrl_delan.training.recorder import RUN_CONFIG

log = logging.getLogger(__name__)

F64 = torch.float64

# a fit's run dir holds, beside its config (RUN_CONFIG), the dataset's provenance and the model
PROVENANCE_FILE = "dataset_provenance.json"
MODEL_FILE = "model.pt"


@dataclass
class GroupErrors:
    """Errors over a group of DoFs."""

    mse: float  # mean over the group's DoFs of the normalised MSE
    mse_si: float  # mean over the group's DoFs of the MSE in SI units
    r2: float  # 1 - sum of normalised SSE / sum of normalised SST over the group's DoFs

    def as_dict(self) -> dict[str, float]:
        return {"mse": self.mse, "mse_si": self.mse_si, "r2": self.r2}


@dataclass
class TorqueErrors:
    """A model's torque errors on one split, per DoF.

    R^2 of a group of DoFs is ``1 - sum_i SSE_i / s_i^2 / sum_i SST_i / s_i^2``, with s the
    training torque scale of the loss and SST about the split's own mean: the share of the
    split's (normalised) torque variance the model explains. A plain mean of per-DoF R^2
    would be ruled by DoFs whose torque hardly varies within a split.
    """

    n: int  # samples
    dof_mse: Tensor  # (nv,) normalised MSE per DoF
    dof_mse_si: Tensor  # (nv,) MSE per DoF in SI units
    dof_var: Tensor  # (nv,) normalised variance of the split's torques per DoF

    @property
    def mse(self) -> float:
        """The loss: normalised MSE over all DoFs."""
        return float(self.dof_mse.mean())

    @property
    def mse_si(self) -> float:
        return float(self.dof_mse_si.mean())

    @property
    def r2(self) -> float:
        return self.group(range(self.dof_mse.shape[0])).r2

    @property
    def dof_r2(self) -> Tensor:
        """Per-DoF R^2 (NaN where the split's torque does not vary). (nv,)"""
        return torch.where(self.dof_var > 0, 1.0 - self.dof_mse / self.dof_var, torch.nan)

    def group(self, dofs: Sequence[int]) -> GroupErrors:
        idx = list(dofs)
        var = float(self.dof_var[idx].sum())
        return GroupErrors(
            mse=float(self.dof_mse[idx].mean()),
            mse_si=float(self.dof_mse_si[idx].mean()),
            r2=1.0 - float(self.dof_mse[idx].sum()) / var if var > 0 else math.nan,
        )


@dataclass
class EpochResult:
    """What one epoch did: its mean training loss and every split's errors afterwards."""

    epoch: int  # counted from 1
    train_loss: float  # sample-weighted mean minibatch loss during the epoch
    wall_time_s: float  # since the start of the fit
    errors: dict[str, TorqueErrors] = field(default_factory=dict)

    def record(self) -> dict[str, float]:
        """Flat record for metrics.jsonl: ``<split>_mse``, ``<split>_mse_si``, ``<split>_r2``."""
        out: dict[str, float] = {
            "epoch": self.epoch,
            "train_loss": self.train_loss,
            "wall_time_s": self.wall_time_s,
        }
        for split, err in self.errors.items():
            out[f"{split}_mse"] = err.mse
            out[f"{split}_mse_si"] = err.mse_si
            out[f"{split}_r2"] = err.r2
        return out


@dataclass
class InverseFitSettings:
    """How `fit_inverse_model` trains."""

    epochs: int = 50
    batch_size: int = 256
    eval_batch_size: int = 2048
    max_grad_norm: float | None = 100.0  # clip the global gradient norm; None: no clipping
    eval_every: int = 1  # evaluate the splits after every k-th epoch and the last; 0: the last
    stop_on: str | None = None  # split evaluated after every epoch: its lowest error is kept
    patience: int | None = None  # with stop_on: epochs without a lower error that end the fit
    min_delta: float = 0.0  # patience restarts only below best - min_delta (normalised MSE)
    min_rel_delta: float = 0.0  # ... and only below best x (1 - min_rel_delta): scale-free

    def __post_init__(self) -> None:
        if self.epochs < 1 or self.batch_size < 1 or self.eval_batch_size < 1:
            raise ValueError(f"epochs and batch sizes must be >= 1: {self}")
        if self.eval_every < 0:
            raise ValueError(f"eval_every must be >= 0: {self}")
        if self.patience is not None and self.patience < 1:
            raise ValueError(f"patience must be >= 1 or None: {self}")
        if not 0.0 <= self.min_delta < math.inf:
            raise ValueError(f"min_delta must be finite and >= 0: {self}")
        if not 0.0 <= self.min_rel_delta < 1.0:
            raise ValueError(f"min_rel_delta must be in [0, 1): {self}")

    def improves(self, error: float, best: float) -> bool:
        """Whether `error` restarts the patience against the lowest error so far `best`:
        lower by more than `min_delta` and by more than the share `min_rel_delta` of it."""
        return error < min(best - self.min_delta, best * (1.0 - self.min_rel_delta))

    def evaluates(self, epoch: int) -> bool:
        """Whether the splits are evaluated after `epoch` (counted from 1)."""
        every = self.eval_every > 0 and epoch % self.eval_every == 0
        return every or epoch == self.epochs


@dataclass
class MassMatrixCheck:
    """Positive definiteness of a learned M over samples."""

    n: int  # samples checked
    positive_definite_fraction: float  # share where torch.linalg.cholesky_ex succeeds
    min_eigenvalue: float  # smallest eigenvalue of M over all samples
    max_condition: float  # largest eigenvalue ratio over all samples

    def as_dict(self) -> dict[str, float]:
        return {
            "n": self.n,
            "positive_definite_fraction": self.positive_definite_fraction,
            "min_eigenvalue": self.min_eigenvalue,
            "max_condition": self.max_condition,
        }


@torch.no_grad()
def evaluate_torques(
    model: InverseDynamicsModel, data: TensorDictBase, batch_size: int = 2048
) -> TorqueErrors:
    """Per-DoF errors of ``model.predict_torque`` on ``data`` (N,) with q, qd, qdd, tau.

    Without autograd: the errors hold no graph (kept for every epoch, they would keep every
    evaluation's graph alive)."""
    model.eval()
    n, nv = data.shape[0], model.nv
    sse, tau_sum, tau_sq = (torch.zeros(nv, dtype=F64) for _ in range(3))
    for idx in batches(n, batch_size, None):
        batch = data[idx.to(data.device)]
        tau = batch[keys.TAU]  # (B, nv)
        pred = model.predict_torque(batch[keys.Q], batch[keys.QD], batch[keys.QDD])
        sse += (pred - tau).to(F64).pow(2).sum(0).cpu()
        tau_sum += tau.to(F64).sum(0).cpu()
        tau_sq += tau.to(F64).pow(2).sum(0).cpu()
    count = max(n, 1)
    mean = tau_sum / count
    var_si = (tau_sq / count - mean.pow(2)).clamp_min(0.0)  # (nv,)
    mse_si = sse / count
    scale2 = model.tau_scale.detach().to(F64).cpu().pow(2)
    return TorqueErrors(n=n, dof_mse=mse_si / scale2, dof_mse_si=mse_si, dof_var=var_si / scale2)


@torch.no_grad()
def check_mass_matrix(model: DeLaNInverse, q: Tensor, batch_size: int = 1024) -> MassMatrixCheck:
    """Cholesky (``torch.linalg.cholesky_ex``) of the learned M at every q (N, nq).

    M is formed in float64 (`DeLaNInverse.mass_matrix_float64`: DeLaN's from its learned
    factor), so the check is not limited by float32 round-off of ill-conditioned matrices.
    """
    model.eval()
    ok, count = 0, 0
    min_eig, max_cond = math.inf, 0.0
    for idx in batches(q.shape[0], batch_size, None):
        M = model.mass_matrix_float64(q[idx.to(q.device)])  # (B, nv, nv)
        info = torch.linalg.cholesky_ex(M).info  # (B,) 0 where M is positive definite
        ok += int((info == 0).sum())
        count += int(info.numel())
        eig = torch.linalg.eigvalsh(M)  # (B, nv) ascending
        min_eig = min(min_eig, float(eig[:, 0].min()))
        max_cond = max(max_cond, float((eig[:, -1] / eig[:, 0].clamp_min(1e-300)).max()))
    return MassMatrixCheck(
        n=count,
        positive_definite_fraction=ok / max(count, 1),
        min_eigenvalue=min_eig,
        max_condition=max_cond,
    )


def train_epoch(
    model: InverseDynamicsModel,
    optimizer: torch.optim.Optimizer,
    data: TensorDictBase,
    settings: InverseFitSettings,
    generator: torch.Generator,
) -> float:
    """One pass over the training data (`training.fit.optimizer_epoch`); the sample-weighted
    mean loss. A NaN/inf loss or gradient norm raises `Diverged` (`fit_inverse_model` turns
    it into `TrainingDivergedError`)."""
    return optimizer_epoch(
        model, optimizer, data, settings.batch_size, settings.max_grad_norm, generator
    )


def _report(results: list[EpochResult], split_names: list[str]) -> FitReport:
    """The epochs so far as a `FitReport` (validation loss: the last split's MSE)."""
    val = split_names[-1] if split_names else None
    return FitReport(
        train_loss=[r.train_loss for r in results],
        val_loss=[r.errors[val].mse for r in results if val in r.errors] if val else [],
        best_epoch=len(results) - 1,
        epochs_run=len(results),
    )


def fit_inverse_model(
    model: InverseDynamicsModel,
    optimizer: torch.optim.Optimizer,
    train: TensorDictBase,
    splits: Mapping[str, TensorDictBase],
    settings: InverseFitSettings,
    generator: torch.Generator,
    on_epoch: Callable[[EpochResult], None] | None = None,
    scheduler: torch.optim.lr_scheduler.LRScheduler | None = None,
    first_epoch: int = 1,
    normalize: bool = True,
) -> list[EpochResult]:
    """Train on ``train`` (N,) for up to ``settings.epochs`` epochs and evaluate every split
    in ``splits`` after the epochs ``settings.evaluates`` names (each one by default, always
    the last); the split ``settings.stop_on`` (if set) after every epoch: the weights of its
    lowest error are restored at the end, and ``settings.patience`` epochs without a lower
    one end the fit.

    ``model.fit_normalization(train)`` is called first when `normalize`. ``on_epoch``
    receives each epoch's result as soon as it is known (for logging); epochs are numbered
    from `first_epoch` (a later stage of a schedule continues the count). ``scheduler``
    steps once per epoch.

    Raises:
        TrainingDivergedError: a loss or gradient norm became NaN/inf; the model holds the
            weights of the last completed epoch (or the initial ones).
        ValueError: ``train`` is empty, or ``stop_on`` is not among ``splits``.
    """
    if train.batch_dims != 1 or train.shape[0] == 0:
        raise ValueError(f"need a non-empty flat training batch (N,), got {train.batch_size}")
    stop_on = settings.stop_on
    if stop_on is not None and stop_on not in splits:
        raise ValueError(f"stop_on={stop_on!r} is not among the splits {list(splits)}")
    if normalize:
        model.fit_normalization(train)
    results: list[EpochResult] = []
    last_good = _weights(model)
    best, best_error, since_best = last_good, math.inf, 0
    start = time.perf_counter()
    for k in range(settings.epochs):
        epoch = first_epoch + k
        try:
            train_loss = train_epoch(model, optimizer, train, settings, generator)
        except Diverged as err:
            model.load_state_dict(last_good)
            raise TrainingDivergedError(
                epoch - 1, err.metric, err.value, _report(results, list(splits)), ""
            ) from None
        if scheduler is not None:
            scheduler.step()
        names = [n for n in splits if settings.evaluates(k + 1) or n == stop_on]
        errors = {n: evaluate_torques(model, splits[n], settings.eval_batch_size) for n in names}
        result = EpochResult(epoch, train_loss, time.perf_counter() - start, errors)
        results.append(result)
        last_good = _weights(model)
        log.info(
            "epoch %d: train loss %.4g; %s",
            epoch,
            train_loss,
            ", ".join(f"{k} mse {v.mse:.4g} (R2 {v.r2:.3f})" for k, v in errors.items()),
        )
        if on_epoch is not None:
            on_epoch(result)
        if stop_on is None:
            continue
        error = errors[stop_on].mse
        since_best = 0 if settings.improves(error, best_error) else since_best + 1
        if error < best_error:
            best, best_error = last_good, error
        if settings.patience is not None and since_best >= settings.patience:
            break
    if stop_on is not None:
        model.load_state_dict(best)
    return results


def _weights(model: InverseDynamicsModel) -> dict[str, Tensor]:
    return {k: v.detach().clone() for k, v in model.state_dict().items()}


def split_summary(errors: TorqueErrors, groups: dict[str, tuple[int, ...]]) -> dict[str, Any]:
    """A split's errors: overall, of the joints (every group but the root) and per group."""
    joints = [i for name, dofs in groups.items() if name != "root" for i in dofs]
    return {
        "n": errors.n,
        "mse": errors.mse,
        "mse_si": errors.mse_si,
        "r2": errors.r2,
        "joint_mse_si": errors.group(joints).mse_si,
        "groups": {name: errors.group(dofs).as_dict() for name, dofs in groups.items()},
    }


def group_errors(
    model: InverseDynamicsModel,
    data: TensorDictBase,
    group_ids: Tensor,
    group_names: list[str],
    batch_size: int,
) -> dict[str, dict[str, float]]:
    """The errors on each clip's or trajectory's samples of one split: n, mse, mse_si, r2
    (R^2 against the group's own torque variance). data (N,), group_ids (N,) indices into
    `group_names`."""
    out = {}
    for group in group_ids.unique().tolist():
        mask = (group_ids == group).to(data.device)
        errors = evaluate_torques(model, data[mask], batch_size)
        out[group_names[group]] = {
            "n": errors.n,
            "mse": errors.mse,
            "mse_si": errors.mse_si,
            "r2": errors.r2,
        }
    return out


GAP_WARNING = 0.01  # a test R^2 this far below the validation split's is warned about


def split_descriptions(provenance: dict[str, Any]) -> dict[str, str]:
    """What each split of an arrays or excitation fit holds, in words (summary.json)."""
    split = provenance.get("split", {})
    whole = split.get("val_by", "trajectories") == "trajectories"
    val = ("whole training trajectories" if whole
           else "one contiguous segment of each training trajectory")  # fmt: skip
    if "test" in provenance:
        test = f"the trajectories of {provenance['test']['path']}"
    elif provenance.get("test_seed") is not None:
        test = (f"trajectories of their own (design {provenance.get('test_design', 'fourier')}, "
                f"seed {provenance['test_seed']})")  # fmt: skip
    else:
        test = "whole trajectories of the data (with fewer than 3: the end of each one)"
    return {"train": "the rest of the data's trajectories", "val": val, "test": test}


def generalisation_gap(final: dict[str, Any], stop_on: str | None) -> float | None:
    """R^2 of the split that stops training less the test split's (None without both); a
    gap above `GAP_WARNING` is warned about: the validation error does not tell the
    held-out one."""
    if stop_on is None or stop_on not in final or "test" not in final:
        return None
    gap = final[stop_on]["r2"] - final["test"]["r2"]
    if gap > GAP_WARNING:
        log.warning(
            "test R2 %.4f is %.4f below %s R2 %.4f: the model does not generalise to the held-"
            "out data as %s says (more varied training data, or %s of whole trajectories)",
            final["test"]["r2"], gap, stop_on, final[stop_on]["r2"], stop_on, stop_on,
        )  # fmt: skip
    return gap


def read_fit_run(run_dir: str | Path) -> tuple[DictConfig, dict[str, torch.Tensor]]:
    """A finished fit's resolved config and its model's state dict (on the CPU).

    Raises FileNotFoundError naming a missing ``config.yaml`` or ``model.pt`` and ValueError
    for a file that is not what a fit writes."""
    run_dir = Path(run_dir)
    config_path, model_path = run_dir / RUN_CONFIG, run_dir / MODEL_FILE
    for path in (config_path, model_path):
        if not path.is_file():
            raise FileNotFoundError(f"no {path.name} in {run_dir} (is it a fit's run dir?)")
    cfg = OmegaConf.load(config_path)
    try:
        saved = torch.load(model_path, map_location="cpu", weights_only=True)
    except (RuntimeError, EOFError, OSError, pickle.UnpicklingError) as err:
        raise ValueError(f"{model_path} is not a readable model file: {err}") from err
    if not isinstance(cfg, DictConfig) or not isinstance(saved, dict) or "state_dict" not in saved:
        raise ValueError(f"{run_dir} does not hold a fit's config.yaml and model.pt")
    return cfg, saved["state_dict"]
