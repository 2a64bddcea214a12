"""The fit's run (`python -m mbrl_delan.fit`'s engine, and its Python API
`fit_inverse_dynamics`): the config checked (`mbrl_delan.conf.fitting`), the data read by
their kind, the model trained (or identified) with every split's errors logged per epoch,
and the run dir written: ``config.yaml``, the dataset's provenance, ``metrics.jsonl``,
``summary.json``, ``model.pt``, the loss curves and, for a model with an MJCF's numbers,
``identified.xml``. A finished fit is read back by `mbrl_delan.runs`."""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDict, TensorDictBase

from mbrl_delan import keys
from mbrl_delan.accelerate.compile import compile_fit
from mbrl_delan.conf.checks import (
    DTYPES,
    ConfigError,
    check_device,
    compose_config,
    refuse_used_run_dir,
)
from mbrl_delan.conf.fitting import (
    FIT_CONFIG_DIR,
    build_system_model,
    data_kind,
    inverse_data,
    validate_fit_config,
)
from mbrl_delan.data.arrays import save_arrays
from mbrl_delan.data.inverse_data import FitSystem, InverseData
from mbrl_delan.data.mocap import random_poses
from mbrl_delan.models.inverse import DeLaNInverse, InverseDynamicsModel
from mbrl_delan.models.rigid_body import WhiteBoxInverse
from mbrl_delan.provenance import provenance
from mbrl_delan.training.identified import (
    IDENTIFIED_FILE,
    identified_numbers,
    identified_summary,
    identified_xml,
)
from mbrl_delan.training.inverse_fit import (
    MODEL_FILE,
    PROVENANCE_FILE,
    EpochResult,
    InverseFitSettings,
    check_mass_matrix,
    evaluate_torques,
    fit_inverse_model,
    generalisation_gap,
    group_errors,
    split_descriptions,
    split_summary,
)
from mbrl_delan.training.recorder import (
    METRICS_FILE,
    RUN_CONFIG,
    SUMMARY_FILE,
    Recorder,
    WandbOptions,
    read_metrics,
)
from mbrl_delan.training.schedule import LearningRateStages, run_stages

log = logging.getLogger(__name__)

RANDOM_POSES = 1024  # poses over the whole joint space where the summary checks a DeLaN's M

# what a fit writes into its run dir; a new fit refuses a folder holding any of them
RUN_FILES = (RUN_CONFIG, PROVENANCE_FILE, MODEL_FILE, METRICS_FILE, SUMMARY_FILE)


def _tensors(td: TensorDictBase, device: torch.device, dtype: torch.dtype) -> TensorDict:
    """The data's float fields on the device in the training dtype. (N,)"""
    return td.to(device=device, dtype=dtype)


def run(cfg: DictConfig, run_dir: Path) -> dict[str, Any]:
    """Validate, build, train and evaluate; write everything into ``run_dir``. The summary.

    The data are read before anything is written: a missing or malformed file leaves the
    run dir as it was."""
    return fit_splits(cfg, run_dir)[0]


def _run(cfg: DictConfig, run_dir: Path) -> tuple[dict[str, Any], InverseDynamicsModel]:
    """`run`; the summary and the trained model."""
    return fit_splits(cfg, run_dir)[:2]


def fit_splits(
    cfg: DictConfig, run_dir: Path
) -> tuple[dict[str, Any], InverseDynamicsModel, dict[str, TensorDict]]:
    """`run`; the summary, the trained model and the splits it was fitted and scored on."""
    validate_fit_config(cfg)
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    device, dtype = check_device(cfg.device), DTYPES[cfg.dtype]
    start, cpu_start = time.perf_counter(), time.process_time()
    stamp = provenance("mbrl_delan.fit")  # the command, the code, the host at the start
    data = inverse_data(cfg.data)
    if cfg.stop_on is not None and data.splits[cfg.stop_on].shape[0] == 0:
        raise ConfigError(f"stop_on={cfg.stop_on!r}: that split of the data is empty")
    run_dir.mkdir(parents=True, exist_ok=True)
    OmegaConf.save(cfg, run_dir / RUN_CONFIG, resolve=True)
    (run_dir / PROVENANCE_FILE).write_text(json.dumps(data.provenance, indent=1))
    splits = {name: _tensors(td, device, dtype) for name, td in data.splits.items()}
    model = build_system_model(cfg, data.system).to(device=device, dtype=dtype)
    if cfg.model.get("compile_fit", False):
        compile_fit(model)
    container = OmegaConf.to_container(cfg, resolve=True)
    logger = cfg.logger
    with Recorder(
        run_dir, logger.backend, logger.project, logger.group, container, step_key="epoch",
        wandb_options=WandbOptions.of(logger),
    ) as recorder:  # fmt: skip
        train_start = time.perf_counter()
        if isinstance(model, WhiteBoxInverse):
            results = [_identify(model, splits, recorder, cfg.eval_batch_size)]
        else:
            results = _train(cfg, model, splits, recorder, device)
        train_s = time.perf_counter() - train_start
        summary = fit_summary(cfg, data, model, splits, results)
        summary["train_s"] = train_s  # training (identification) with its evaluations
        summary["wall_time_s"] = time.perf_counter() - start
        summary["cpu_time_s"] = time.process_time() - cpu_start  # all threads (threads=1: one core)
        summary |= stamp
        recorder.write_summary(summary)
        _write_identified(model, data.system, run_dir)
        recorder.log_image("loss_curves", _save_model_and_curves(cfg, model, run_dir))
        recorder.log_artifact(run_dir / MODEL_FILE)
    _log_summary(run_dir, summary)
    return summary, model, splits


def _settings(cfg: DictConfig, epochs: int) -> InverseFitSettings:
    return InverseFitSettings(
        epochs=epochs,
        batch_size=cfg.batch_size,
        eval_batch_size=cfg.eval_batch_size,
        max_grad_norm=cfg.max_grad_norm,
        eval_every=cfg.eval_every,
        stop_on=cfg.stop_on,
        patience=cfg.patience,
        min_delta=cfg.min_delta,
        min_rel_delta=cfg.min_rel_delta,
    )


def _train(
    cfg: DictConfig,
    model: InverseDynamicsModel,
    splits: dict[str, TensorDict],
    recorder: Recorder,
    device: torch.device,
) -> list[EpochResult]:
    """Adam on the training split at ``cfg.lr`` (``lr_schedule``: constant, cosine down to 0,
    or `LearningRateStages`); the non-empty splits evaluated and logged per epoch."""
    optimizer = torch.optim.Adam(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    generator = torch.Generator(device=device).manual_seed(cfg.seed)
    evaluated = {k: v for k, v in splits.items() if v.shape[0] > 0}
    results: list[EpochResult] = []

    def on_epoch(result: EpochResult) -> None:
        recorder.log(result.record(), result.epoch)

    def fit(epochs: int, scheduler: Any = None) -> int:
        done = fit_inverse_model(
            model,
            optimizer,
            splits["train"],
            evaluated,
            _settings(cfg, epochs),
            generator,
            on_epoch,
            scheduler,
            first_epoch=len(results) + 1,
            normalize=not results,
        )
        results.extend(done)
        return len(done)

    if cfg.lr_schedule == "stages":
        schedule = LearningRateStages(
            lr=cfg.lr,
            stages=cfg.stages.count,
            decay=cfg.stages.decay,
            warmup_steps=cfg.stages.warmup_steps,
            max_epochs=cfg.epochs,
        )
        run_stages(optimizer, schedule, lambda stage, epochs: fit(epochs))
    elif cfg.lr_schedule == "cosine":  # from lr down to 0 over the epochs
        fit(cfg.epochs, torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, T_max=cfg.epochs))
    else:
        fit(cfg.epochs)
    return results


def _identify(
    model: WhiteBoxInverse, splits: dict[str, TensorDict], recorder: Recorder, batch_size: int
) -> EpochResult:
    """The white box identified on the training split (one step, logged as epoch 1)."""
    start = time.perf_counter()
    model.fit_normalization(splits["train"])
    found = model.identify(splits["train"])
    errors = {k: evaluate_torques(model, v, batch_size) for k, v in splits.items() if v.shape[0]}
    result = EpochResult(1, found.mse, time.perf_counter() - start, errors)
    recorder.log(result.record(), result.epoch)
    return result


def _save_model_and_curves(cfg: DictConfig, model: InverseDynamicsModel, run_dir: Path) -> Path:
    """``model.pt`` (state dict) and ``loss_curves.png`` from ``metrics.jsonl`` (returned)."""
    from mbrl_delan.training.fit_plots import LOSS_CURVES_PNG, plot_loss_curves  # matplotlib

    torch.save({"model": cfg.model.name, "state_dict": model.state_dict()}, run_dir / MODEL_FILE)
    records = read_metrics(run_dir / METRICS_FILE)
    plot_loss_curves({cfg.model.name: records}, run_dir / LOSS_CURVES_PNG)
    return run_dir / LOSS_CURVES_PNG


def fit_summary(
    cfg: DictConfig,
    data: InverseData,
    model: InverseDynamicsModel,
    splits: dict[str, TensorDict],
    results: list[EpochResult],
) -> dict[str, Any]:
    """summary.json: the kept weights' errors on every non-empty split (overall, per DoF group
    and per clip or trajectory), sizes, and DeLaN's M checks."""
    groups = data.system.dof_groups
    final = {
        name: evaluate_torques(model, td, cfg.eval_batch_size)
        for name, td in splits.items()
        if td.shape[0] > 0
    }
    best = min(results, key=lambda r: r.errors[cfg.stop_on].mse) if cfg.stop_on else results[-1]
    provenance, kind = data.provenance, data_kind(cfg.data)
    summary: dict[str, Any] = {
        "data": cfg.data.name,
        "model": cfg.model.name,
        "seed": cfg.seed,
        "device": cfg.device,
        "dtype": cfg.dtype,
        "epochs": len(results),
        "best_epoch": best.epoch,
        "stop_on": cfg.stop_on,
        "n_parameters": sum(p.numel() for p in model.parameters()),
        "samples": {name: int(td.shape[0]) for name, td in splits.items()},
        "tau": kind.tau,
        "loss": f"per-DoF normalised torque MSE, std floored at {cfg.loss.std_floor} x the largest",
        "dof_groups": {name: len(dofs) for name, dofs in groups.items()},
        "final": {name: split_summary(err, groups) for name, err in final.items()},
    }
    summary |= kind.summary(provenance)
    if data.group_kind == "trajectories":
        summary |= {"trajectories": len(data.group_names),
                    "splits": split_descriptions(provenance)}  # fmt: skip
    for name, part in summary["final"].items():
        part[data.group_kind] = group_errors(
            model, splits[name], data.groups[name], data.group_names, cfg.eval_batch_size
        )
        summary[f"{name}_mse"] = part["mse"]
        summary[f"{name}_mse_si"] = part["mse_si"]
        summary[f"{name}_r2"] = part["r2"]
    gap = generalisation_gap(summary["final"], cfg.stop_on)
    if gap is not None:
        summary["val_test_r2_gap"] = gap
    if isinstance(model, DeLaNInverse):
        q_all = torch.cat([td[keys.Q] for td in splits.values()])
        check = check_mass_matrix(model, q_all, cfg.eval_batch_size)
        summary["mass_matrix"] = check.as_dict()
        summary["positive_definite_fraction"] = check.positive_definite_fraction
        if data.system.mj_model is not None:
            poses = random_poses(data.system.mj_model, RANDOM_POSES).to(q_all)  # off the data
            summary["mass_matrix_random_poses"] = check_mass_matrix(model, poses).as_dict()
    numbers = identified_numbers(model)
    if numbers is not None and data.system.mj_model is not None:
        test = splits.get("test")
        test = test if test is not None and test.shape[0] else None
        summary["identified"] = identified_summary(model, numbers, data.system.mj_model, test) | (
            model.identified() if isinstance(model, WhiteBoxInverse) else {}
        )
    if kind.mass_matrix_error is not None and isinstance(model, DeLaNInverse | WhiteBoxInverse):
        summary["mass_matrix_error"] = _mass_matrix_errors(cfg.data, model, splits)  # the arm's
    return summary


def _write_identified(model: InverseDynamicsModel, system: FitSystem, run_dir: Path) -> None:
    """``identified.xml`` (`mbrl_delan.training.identified`) for a model with an MJCF's
    numbers: the white box and DeLaN on the tree."""
    numbers = identified_numbers(model)
    spec = None if numbers is None else system.mjcf_spec()
    if spec is not None:
        (run_dir / IDENTIFIED_FILE).write_text(identified_xml(spec, numbers))


def _mass_matrix_errors(
    data: DictConfig, model: DeLaNInverse | WhiteBoxInverse, splits: dict[str, TensorDictBase]
) -> dict[str, float]:
    """Per non-empty split: the median relative Frobenius error of the learned M against
    the arm's (`data.excitation.mass_matrix_error`)."""
    out = {}
    for name, td in splits.items():
        if td.shape[0] == 0:
            continue
        q = td[keys.Q]
        with torch.no_grad():
            mass = model.mass_matrix(q).to("cpu", torch.float64).numpy()
        q64 = q.to("cpu", torch.float64).numpy()
        out[name] = data_kind(data).mass_matrix_error(data, q64, mass)
    return out


def _log_summary(run_dir: Path, s: dict[str, Any]) -> None:
    log.info("run dir: %s", run_dir)
    for name, part in s["final"].items():
        log.info(
            "%s after %d epochs, %s: MSE %.4g (normalised), %.4g (SI), R2 %.3f (%d samples)",
            s["model"],
            s["epochs"],
            name,
            part["mse"],
            part["mse_si"],
            part["r2"],
            part["n"],
        )
    if "positive_definite_fraction" in s:
        log.info(
            "DeLaN: M positive definite on %.4f of %d samples",
            s["positive_definite_fraction"],
            s["mass_matrix"]["n"],
        )
    for name, error in s.get("mass_matrix_error", {}).items():
        log.info("M's median relative error against the arm's, %s: %.4f", name, error)
    log.info("wall time %.1f s (CPU time %.1f s)", s["wall_time_s"], s["cpu_time_s"])


@dataclass
class FitResult:
    """What `fit_inverse_dynamics` returns: the run's config, trained model, summary, dir."""

    config: DictConfig
    model: InverseDynamicsModel
    summary: dict[str, Any]
    run_dir: Path


def fit_inverse_dynamics(
    data: str | Path | Mapping[str, Any],
    joints: Sequence[str] | str,
    run_dir: str | Path,
    model: str = "delan",
    overrides: Sequence[str] = (),
) -> FitResult:
    """``python -m mbrl_delan.fit data=arrays`` from Python, with its defaults.

    Args:
        data: a data file (`mbrl_delan.data.arrays`' schema) or its fields in memory (a dict
            or TensorDict of arrays or tensors: q, qd, tau, ...; written to
            ``run_dir/data.npz``).
        joints: the joint types in order (``["hinge", "hinge"]``), or an MJCF file or the
            stem of a shipped model (``"arm2"``).
        run_dir: where the run's files go (refused if it holds a run already).
        model: ``delan``, ``mlp`` or ``ensemble``.
        overrides: further config overrides as on the command line (``["epochs=100"]``).

    Raises ConfigError for a bad config value, FileNotFoundError and ArrayFormatError for a
    missing or malformed data file, TrainingDivergedError when the fit diverges.
    """
    run_dir = Path(run_dir)
    refuse_used_run_dir(run_dir, RUN_FILES, "give another run_dir")
    if not isinstance(data, str | Path):
        run_dir.mkdir(parents=True, exist_ok=True)
        data = save_arrays(data, run_dir / "data.npz")
    joint_key = (
        f"data.mjcf={joints}"
        if isinstance(joints, str)
        else "data.joints=[" + ",".join(joints) + "]"
    )
    base = ["data=arrays", f"data.path={Path(data)}", joint_key, f"model={model}", "logger=none"]
    cfg = compose_config(FIT_CONFIG_DIR, [*base, *overrides])
    summary, trained = _run(cfg, run_dir)
    return FitResult(config=cfg, model=trained, summary=summary, run_dir=run_dir)
