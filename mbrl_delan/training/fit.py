"""Fitting a world model on a dataset of transitions.

Epochs of shuffled minibatches, a validation split that keeps each sample on its side as the
data grows, early stopping on the validation loss, best-weights restoring, gradient clipping
and a loud failure on NaN/inf.
"""

from __future__ import annotations

import copy
import logging
import math
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from typing import Any

import torch
from tensordict import TensorDictBase
from torch import Tensor, nn

from mbrl_delan import keys
from mbrl_delan.models.base import WorldModel

log = logging.getLogger(__name__)


@dataclass
class FitConfig:
    """How ``fit_model`` trains.

    Attributes:
        batch_size: transitions per minibatch (training and validation).
        max_epochs: upper bound on the number of epochs.
        val_fraction: share of the data held out for validation, in [0, 1); which samples,
            is fixed by their index (`_split`), so a growing buffer keeps its split.
        min_val_size: fewest validation transitions worth a split; with fewer (or with
            ``val_fraction == 0``) the model is validated on the training data.
        patience: epochs without improvement before stopping; ``None`` never stops early.
        min_delta: a validation loss counts as an improvement when it is below the best so far
            by more than this (absolute) amount.
        max_grad_norm: gradients are clipped to this global L2 norm; ``None`` does not clip.
        max_batches_per_epoch: cap on optimizer steps per epoch (for large buffers); ``None``
            goes through all training data once per epoch.
        rollout_steps: K, the model steps of each training sample. 1: single transitions.
            K > 1: windows of K consecutive transitions, the model rolled out K steps from
            each window's first state on its actions and scored on every state it reaches
            (a multi-step loss against compounding error; models with `trains_on_windows`).
    """

    # metadata: the valid range, as the config checks read it (`mbrl_delan.conf.schema.rule`)
    batch_size: int = field(default=256, metadata={"low": 1})
    max_epochs: int = field(default=100, metadata={"low": 1})
    val_fraction: float = field(default=0.1, metadata={"low": 0, "high": 1, "below": True})
    min_val_size: int = field(default=1, metadata={"low": 0})
    patience: int | None = field(default=10, metadata={"low": 1})
    min_delta: float = field(default=0.0, metadata={"low": 0})
    max_grad_norm: float | None = field(default=10.0, metadata={"low": 0, "above": True})
    max_batches_per_epoch: int | None = field(default=None, metadata={"low": 1})
    rollout_steps: int = field(default=1, metadata={"low": 1})

    def __post_init__(self) -> None:
        if self.rollout_steps < 1:
            raise ValueError(f"rollout_steps must be >= 1, got {self.rollout_steps}")
        if self.batch_size <= 0 or self.max_epochs <= 0:
            raise ValueError("batch_size and max_epochs must be positive")
        if not 0.0 <= self.val_fraction < 1.0:
            raise ValueError(f"val_fraction must be in [0, 1), got {self.val_fraction}")
        if self.patience is not None and self.patience <= 0:
            raise ValueError(f"patience must be positive or None, got {self.patience}")
        if self.min_val_size < 0 or not self.min_delta >= 0:
            raise ValueError(
                f"min_val_size and min_delta must be >= 0, got {self.min_val_size}, "
                f"{self.min_delta}"
            )
        if self.max_grad_norm is not None and not self.max_grad_norm > 0:
            raise ValueError(f"max_grad_norm must be > 0 or None, got {self.max_grad_norm}")
        if self.max_batches_per_epoch is not None and self.max_batches_per_epoch < 1:
            raise ValueError(
                f"max_batches_per_epoch must be >= 1 or None, got {self.max_batches_per_epoch}"
            )


@dataclass
class FitReport:
    """What happened during ``fit_model``. Epochs are counted from 0.

    Attributes:
        train_loss: mean training loss per epoch.
        val_loss: mean validation loss per epoch (after that epoch's updates).
        best_epoch: epoch whose weights were restored (lowest validation loss); -1 if none.
        best_val_loss: its validation loss.
        epochs_run: number of completed epochs.
        stopped_early: training stopped because of ``patience``.
        validated_on_train: the data were too few for a split and validation used train data.
        n_train: training samples (transitions, or windows with `rollout_steps` > 1).
        n_val: validation samples.
        metrics: ``LossOutput.metrics`` of the restored weights, averaged over validation data.
        warmup: with ``rollout_steps`` > 1, the report of the one-step fit that came first.
    """

    train_loss: list[float] = field(default_factory=list)
    val_loss: list[float] = field(default_factory=list)
    best_epoch: int = -1
    best_val_loss: float = math.inf
    epochs_run: int = 0
    stopped_early: bool = False
    validated_on_train: bool = False
    n_train: int = 0
    n_val: int = 0
    metrics: dict[str, float] = field(default_factory=dict)
    warmup: FitReport | None = None


class TrainingDivergedError(RuntimeError):
    """The loss or gradient became NaN/inf. The model holds its last good weights again.

    Attributes:
        epoch: epoch (from 0) in which it happened.
        metric: name of the offending quantity ("train_loss", "grad_norm", "val_loss", ...).
        value: its value.
        report: the fit report up to the last completed epoch.
    """

    def __init__(self, epoch: int, metric: str, value: float, report: FitReport, detail: str):
        self.epoch = epoch
        self.metric = metric
        self.value = value
        self.report = report
        super().__init__(
            f"training diverged in epoch {epoch} (counted from 0): {metric} = {value}{detail}. "
            f"Weights restored from epoch {report.best_epoch} "
            f"({'initial weights' if report.best_epoch < 0 else 'best validation loss'})."
        )


class Diverged(Exception):
    """A non-finite loss or gradient norm during fitting; the fit entry points catch it."""

    def __init__(self, metric: str, value: float, detail: str = ""):
        super().__init__(metric)
        self.metric = metric
        self.value = value
        self.detail = detail


@dataclass
class _Snapshot:
    model: dict[str, Tensor]
    optimizer: dict[str, Any]


def _snapshot(model: WorldModel, optimizer: torch.optim.Optimizer) -> _Snapshot:
    weights = {k: v.detach().clone() for k, v in model.state_dict().items()}
    return _Snapshot(weights, copy.deepcopy(optimizer.state_dict()))


def window_starts(data: TensorDictBase, steps: int) -> Tensor:
    """Where each window of `steps` consecutive transitions starts in time-ordered
    transitions (N,). Transition i + 1 follows transition i when its state is exactly i's
    next state (so episode ends and a replay buffer's wrap-around split windows). -> (M,),
    M <= N, increasing."""
    n = data.shape[0]
    first = torch.arange(max(n - steps + 1, 0), device=data[keys.Q].device)  # (N-K+1,)
    if steps == 1:
        return first
    follows = (data[keys.NEXT_Q][:-1] == data[keys.Q][1:]).all(-1) & (
        data[keys.NEXT_QD][:-1] == data[keys.QD][1:]
    ).all(-1)  # (N-1,)
    links = torch.cat([follows.new_zeros(1, dtype=torch.long), follows.long().cumsum(0)])  # (N,)
    return first[links[first + steps - 1] - links[first] == steps - 1]


def transition_windows(
    data: TensorDictBase, steps: int, starts: Tensor | None = None
) -> TensorDictBase:
    """Every window of `steps` consecutive transitions (at `starts`, default
    `window_starts`). -> (M, steps)."""
    if steps == 1:
        return data.unsqueeze(-1)
    if starts is None:
        starts = window_starts(data, steps)
    return data[starts.unsqueeze(-1) + torch.arange(steps, device=starts.device)]


# the fractional part of i * (sqrt(5) - 1) / 2 spreads the indices i evenly over [0, 1)
_SPLIT_STRIDE = (math.sqrt(5.0) - 1.0) / 2.0


def _split(ids: Tensor, cfg: FitConfig) -> tuple[Tensor, Tensor, bool]:
    """Train / validation positions (CPU int64) of samples with running numbers `ids` (N,);
    the bool says val == train.

    Sample i is held out when frac(i * 0.618...) < val_fraction: a function of its running
    number alone (its place among all transitions ever added), so in the loop's refits a
    transition that validated one fit never trains a later one and none that trained one
    validates a later one, also once a full replay buffer drops its oldest transitions.
    (A fresh random split per refit would score a warm-started model on data it has just
    fitted, and stop its training early.)"""
    ids = ids.cpu()
    index = torch.arange(ids.numel(), dtype=torch.long)
    held_out = torch.frac(ids.double() * _SPLIT_STRIDE) < cfg.val_fraction  # (N,)
    n_val = int(held_out.sum())
    if n_val < max(cfg.min_val_size, 1) or ids.numel() - n_val < 1:
        return index, index, True
    return index[~held_out], index[held_out], False


def batches(
    n: int, batch_size: int, generator: torch.Generator | None, max_batches: int | None = None
) -> Iterator[Tensor]:
    """Index tensors of minibatches; shuffled when a generator is given."""
    if generator is None:
        order = torch.arange(n)
    else:
        order = torch.randperm(n, generator=generator, device=generator.device).cpu()
    for i, start in enumerate(range(0, n, batch_size)):
        if max_batches is not None and i >= max_batches:
            return
        yield order[start : start + batch_size]


def _nonfinite_metrics(metrics: dict[str, float]) -> str:
    bad = {k: v for k, v in metrics.items() if not math.isfinite(v)}
    return f" (non-finite metrics: {bad})" if bad else ""


def optimizer_epoch(
    model: nn.Module,
    optimizer: torch.optim.Optimizer,
    data: TensorDictBase,
    batch_size: int,
    max_grad_norm: float | None,
    generator: torch.Generator,
    max_batches: int | None = None,
) -> float:
    """One pass of shuffled minibatches (`model.loss`, backward, gradient clipping, optimizer
    step); the sample-weighted mean loss. A non-finite loss or gradient norm raises `Diverged`."""
    model.train()
    params = [p for p in model.parameters() if p.requires_grad]
    max_norm = math.inf if max_grad_norm is None else max_grad_norm
    total, count = 0.0, 0
    for idx in batches(data.shape[0], batch_size, generator, max_batches):
        out = model.loss(data[idx.to(data.device)])
        loss_value = float(out.loss.detach())
        if not math.isfinite(loss_value):
            raise Diverged("train_loss", loss_value, _nonfinite_metrics(out.metrics))
        optimizer.zero_grad(set_to_none=True)
        out.loss.backward()
        grad_norm = float(torch.nn.utils.clip_grad_norm_(params, max_norm))
        if not math.isfinite(grad_norm):
            raise Diverged("grad_norm", grad_norm)
        optimizer.step()
        total += loss_value * len(idx)
        count += len(idx)
    return total / max(count, 1)


def _evaluate(
    model: WorldModel, data: TensorDictBase, batch_size: int
) -> tuple[float, dict[str, float]]:
    """Sample-weighted mean loss and metrics, without optimizer steps.

    Autograd stays on: some models differentiate inside their forward pass.
    """
    model.eval()
    total, count = 0.0, 0
    sums: dict[str, float] = {}
    with torch.enable_grad():
        for idx in batches(data.shape[0], batch_size, None):
            out = model.loss(data[idx])
            n = len(idx)
            total += float(out.loss.detach()) * n
            count += n
            for name, value in out.metrics.items():
                sums[name] = sums.get(name, 0.0) + float(value) * n
    model.zero_grad(set_to_none=True)
    return total / count, {k: v / count for k, v in sums.items()}


def _check_val(loss: float, metrics: dict[str, float]) -> None:
    if not math.isfinite(loss):
        raise Diverged("val_loss", loss, _nonfinite_metrics(metrics))


def _windows(model: WorldModel, data: TensorDictBase, steps: int) -> tuple[TensorDictBase, Tensor]:
    """The windows (M, steps) of transitions (N,) that a K-step fit trains on, and the
    position of each one's first transition (M,)."""
    if not model.trains_on_windows:
        raise ValueError(
            f"fit rollout_steps={steps} needs a model that trains on windows of transitions "
            f"(DeLaN with the forward loss); {type(model).__name__} trains on single ones"
        )
    starts = window_starts(data, steps)
    if starts.numel() == 0:
        raise ValueError(
            f"fit rollout_steps={steps}: the {data.shape[0]} transitions hold no run of "
            f"{steps} consecutive ones (each one's next state the following one's state)"
        )
    return transition_windows(data, steps, starts), starts


def fit_model(
    model: WorldModel,
    optimizer: torch.optim.Optimizer,
    data: TensorDictBase,
    cfg: FitConfig,
    generator: torch.Generator,
    first_index: int = 0,
) -> FitReport:
    """Train ``model`` on transitions ``data`` (batch shape (N,), time-ordered when
    ``cfg.rollout_steps > 1``) and keep its best weights.

    ``first_index``: the running number of ``data[0]`` among all transitions ever added
    (the loop passes how many have left its full replay buffer), so that the validation
    split, fixed by each transition's running number (`_split`), stays fixed once the
    buffer drops its oldest transitions.

    Calls ``model.fit_normalization`` on the training part, then runs up to ``cfg.max_epochs``
    epochs of shuffled minibatches (the shuffling uses ``generator`` only; the validation
    split is fixed by each sample's running number, see `_split`). After every epoch the validation
    loss decides the best weights, which are restored at the end.

    With ``cfg.rollout_steps`` K > 1 this is done twice: on single transitions first (a
    K-step rollout of an untrained model can overflow), then on windows of K transitions
    from the best one-step weights, keeping the one-step normalisation. The report is the
    K-step fit's, with the one-step fit's as ``warmup``.

    Raises:
        TrainingDivergedError: a loss or gradient norm became NaN/inf. The model (and the
            optimizer's state) are first restored to the best weights so far, or to the
            initial ones when no epoch completed.
        ValueError: ``data`` is empty, or holds no window of K consecutive transitions, or
            the model does not train on windows.
    """
    if data.batch_dims != 1 or data.shape[0] == 0:
        raise ValueError(f"fit_model needs a non-empty flat batch (N,), got {data.batch_size}")
    if first_index < 0:
        raise ValueError(f"first_index must be >= 0, got {first_index}")
    ids = first_index + torch.arange(data.shape[0])  # (N,) running numbers
    if cfg.rollout_steps == 1:
        return _fit(model, optimizer, data, ids, cfg, generator)
    windows, starts = _windows(model, data, cfg.rollout_steps)
    warmup = _fit(model, optimizer, data, ids, replace(cfg, rollout_steps=1), generator)
    report = _fit(
        model, optimizer, windows, first_index + starts.cpu(), cfg, generator, normalize=False
    )
    report.warmup = warmup
    return report


def _fit(
    model: WorldModel,
    optimizer: torch.optim.Optimizer,
    data: TensorDictBase,
    ids: Tensor,
    cfg: FitConfig,
    generator: torch.Generator,
    normalize: bool = True,
) -> FitReport:
    """`fit_model` on samples (N,) or windows (M, K) with running numbers `ids` (N,) or
    (M,) (a window's: its first transition's); `normalize`: call fit_normalization."""
    was_training = model.training
    train_idx, val_idx, on_train = _split(ids, cfg)
    train_data = data[train_idx]
    val_data = train_data if on_train else data[val_idx]
    report = FitReport(validated_on_train=on_train, n_train=len(train_idx), n_val=len(val_idx))
    if on_train:
        log.warning(
            "only %d samples: too few for a validation split (val_fraction=%s); "
            "validating on the training data",
            data.shape[0],
            cfg.val_fraction,
        )
    if normalize:
        model.fit_normalization(train_data)
    best = _snapshot(model, optimizer)
    epoch = 0
    try:
        for epoch in range(cfg.max_epochs):
            train_loss = optimizer_epoch(
                model,
                optimizer,
                train_data,
                cfg.batch_size,
                cfg.max_grad_norm,
                generator,
                cfg.max_batches_per_epoch,
            )
            val_loss, metrics = _evaluate(model, val_data, cfg.batch_size)
            _check_val(val_loss, metrics)
            report.train_loss.append(train_loss)
            report.val_loss.append(val_loss)
            report.epochs_run = epoch + 1
            if val_loss < report.best_val_loss - cfg.min_delta:
                report.best_epoch, report.best_val_loss, report.metrics = epoch, val_loss, metrics
                best = _snapshot(model, optimizer)
            elif cfg.patience is not None and epoch - report.best_epoch >= cfg.patience:
                report.stopped_early = True
                break
    except Diverged as err:
        model.load_state_dict(best.model)
        optimizer.load_state_dict(best.optimizer)
        model.train(was_training)
        raise TrainingDivergedError(epoch, err.metric, err.value, report, err.detail) from None
    model.load_state_dict(best.model)
    model.train(was_training)
    log.info(
        "fit: %d epochs%s, best epoch %d, val loss %.4g (%d train / %d val %s)",
        report.epochs_run,
        " (stopped early)" if report.stopped_early else "",
        report.best_epoch,
        report.best_val_loss,
        report.n_train,
        report.n_val,
        "transitions" if cfg.rollout_steps == 1 else f"windows of {cfg.rollout_steps} steps",
    )
    return report
