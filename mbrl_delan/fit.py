"""`python -m mbrl_delan.fit data=cmu_mocap model=delan|mlp|ensemble`: inverse dynamics from mocap.

The paper's experiment: learn a humanoid's inverse dynamics ``(q, qd, qdd) -> tau`` from CMU
motion capture with DeLaN and with a feed-forward network, and compare their training and
validation losses per epoch. The config tree is ``configs/fit`` (``model=`` names an
inverse-dynamics model of `mbrl_delan.models.inverse` here).

Builds (or loads) the mocap dataset, trains the model on its training part and evaluates it on
every split after each epoch. The run dir (``runs/fit/...``) receives ``config.yaml``,
``dataset_provenance.json``, ``metrics.jsonl`` (one record per epoch), ``summary.json``
(final errors per split and body part; DeLaN's positive-definiteness check), ``model.pt``
and ``loss_curves.png``. Compare runs with ``python -m mbrl_delan.fit_report``.

Exit codes: 0 done, 2 bad config value or missing clip/dataset, 1 bad data (NaN, malformed
file, unstable PD tracking) or diverged training.
"""

from __future__ import annotations

import json
import logging
import pickle
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import hydra
import mujoco
import torch
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, ListConfig, OmegaConf
from tensordict import TensorDict, TensorDictBase
from torch import Tensor

from mbrl_delan import keys
from mbrl_delan.accelerate.compile import compile_fit
from mbrl_delan.config import (
    CONFIG_DIR,
    DTYPES,
    ConfigError,
    check_device,
    check_number,
    check_whole,
    exit_on_config_errors,
    refuse_used_run_dir,
)
from mbrl_delan.data.buffer import NonFiniteDataError, check_finite
from mbrl_delan.data.mocap import (
    GAINS,
    SPLIT_NAMES,
    TORQUE_SOURCES,
    ClipNotFoundError,
    FilterSettings,
    MocapDataset,
    MocapFormatError,
    TrackingSettings,
    TrackingUnstableError,
    build_dataset,
    dof_groups,
    humanoid_cmu_xml,
    load_dataset,
    random_poses,
    split_dataset,
)
from mbrl_delan.data.mocap.retarget import joint_layout
from mbrl_delan.models.inverse import (
    MLP_ACTIVATIONS,
    MODEL_NAMES,
    DeLaNInverse,
    InverseDynamicsModel,
    MLPEnsembleInverse,
    MLPInverse,
)
from mbrl_delan.models.structure import Structure
from mbrl_delan.models.tangent_mlp import ACTIVATIONS as DELAN_ACTIVATIONS
from mbrl_delan.systems.system import JointLayout
from mbrl_delan.training.fit import TrainingDivergedError
from mbrl_delan.training.inverse_fit import (
    EpochResult,
    InverseFitSettings,
    TorqueErrors,
    check_mass_matrix,
    evaluate_torques,
    fit_inverse_model,
)
from mbrl_delan.training.recorder import (
    METRICS_FILE,
    RUN_CONFIG,
    SUMMARY_FILE,
    Recorder,
    read_metrics,
)

log = logging.getLogger("mbrl_delan.fit")

DATA_NAMES = ("cmu_mocap",)
LR_SCHEDULES = ("constant", "cosine")
PROVENANCE_FILE = "dataset_provenance.json"
RANDOM_POSES = 1024  # poses over the whole joint space where the summary checks a DeLaN's M
MODEL_FILE = "model.pt"
# what a fit writes into its run dir; a new fit refuses a folder holding any of them
RUN_FILES = (RUN_CONFIG, PROVENANCE_FILE, MODEL_FILE, METRICS_FILE, SUMMARY_FILE)
FIT_CONFIG_DIR = CONFIG_DIR / "fit"  # this entry point's YAML files
SPLITS = tuple(SPLIT_NAMES.values())  # ("train", "val_time", "val_clip")
TAU_DEFINITION = (
    "all nv generalized forces (humanoid_CMU: 62 = 6 root residual [world-frame force, "
    "body-frame torque] + 56 hinge torques), the dataset's tau"
)


# ---------------------------------------------------------------- config checking


def _choice(path: str, value: Any, choices: Sequence[str]) -> None:
    if value not in choices:
        raise ConfigError(f"{path}={value!r} is not valid; choose one of: {', '.join(choices)}")


def _flag(path: str, value: Any) -> None:
    if not isinstance(value, bool):
        raise ConfigError(f"{path}={value!r} is not valid; it must be true or false")


def _clip_names(path: str, value: Any, allow_empty: bool = False) -> list[str]:
    if not isinstance(value, list | tuple | ListConfig) or (not value and not allow_empty):
        raise ConfigError(
            f"{path}={value!r} is not valid; give a list of clip names (subject_trial)"
        )
    for i, name in enumerate(value):
        if not isinstance(name, str):
            raise ConfigError(
                f"{path}[{i}]={name!r} is not a clip name; quote names like '131_03' "
                "(Hydra reads 131_03 as the number 13103)"
            )
    return [str(v) for v in value]


def _validate_model(cfg: DictConfig) -> None:
    _choice("model.name", cfg.name, MODEL_NAMES)
    check_number("model.hidden", cfg.hidden, 1)
    if cfg.name == "delan":
        check_number("model.layers", cfg.layers, 1)
        _choice("model.activation", cfg.activation, DELAN_ACTIVATIONS)
        check_number("model.diag_shift", cfg.diag_shift, 0.0, open_low=True)
        _flag("model.still_first_order", cfg.still_first_order)
        _flag("model.tree_sparse", cfg.tree_sparse)
        _flag("model.armature", cfg.get("armature", False))
        _flag("model.compile_fit", cfg.get("compile_fit", False))
    else:
        _choice("model.activation", cfg.activation, tuple(MLP_ACTIVATIONS))
    if cfg.name == "ensemble":
        check_number("model.ensemble_size", cfg.ensemble_size, 1)


def _validate_data(cfg: DictConfig) -> None:
    _choice("data.name", cfg.name, DATA_NAMES)
    _choice("data.torques", cfg.torques, TORQUE_SOURCES)
    _flag("data.skip_bad_clips", cfg.skip_bad_clips)
    if cfg.dataset_dir is not None:
        return
    clips = _clip_names("data.clips", cfg.clips)
    val = _clip_names("data.val_clips", cfg.val_clips, allow_empty=True)
    unknown = [c for c in val if c not in clips]
    if unknown:
        raise ConfigError(f"data.val_clips={val} is not valid: {unknown} not in data.clips={clips}")
    if len(set(clips)) != len(clips):
        raise ConfigError(f"data.clips={clips} is not valid: a clip is listed twice")
    if cfg.samples_per_clip is not None:
        check_number("data.samples_per_clip", cfg.samples_per_clip, 1)
    if cfg.filter.cutoff_hz is not None:
        check_number("data.filter.cutoff_hz", cfg.filter.cutoff_hz, 0.0, 59.99, open_low=True)
    check_number("data.filter.order", cfg.filter.order, 1)
    check_number("data.filter.edge_trim_s", cfg.filter.edge_trim_s, 0.0)
    check_number("data.split.val_time_fraction", cfg.split.val_time_fraction, 0.0, 0.95)
    check_number("data.split.gap_s", cfg.split.gap_s, 0.0)
    check_number("data.glitch.deg", cfg.glitch.deg, 0.0, open_low=True)
    check_number("data.glitch.pad_s", cfg.glitch.pad_s, 0.0)
    if cfg.torques == "pd":
        check_number("data.pd.omega", cfg.pd.omega, 0.0, open_low=True)
        check_number("data.pd.zeta", cfg.pd.zeta, 0.0, open_low=True)
        _choice("data.pd.gains", cfg.pd.gains, GAINS)


def validate_fit_config(cfg: DictConfig) -> None:
    """Every value the fit entry point uses, checked before anything is built or written."""
    _choice("dtype", cfg.dtype, tuple(DTYPES))
    check_device(cfg.device)
    check_whole("seed", cfg.seed, 0)
    check_whole("threads", cfg.threads, 1, optional=True)
    check_number("epochs", cfg.epochs, 1)
    check_whole("eval_every", cfg.eval_every, 0)
    check_number("batch_size", cfg.batch_size, 1)
    check_number("eval_batch_size", cfg.eval_batch_size, 1)
    check_number("lr", cfg.lr, 0.0, open_low=True)
    check_number("weight_decay", cfg.weight_decay, 0.0)
    _choice("lr_schedule", cfg.lr_schedule, LR_SCHEDULES)
    if cfg.max_grad_norm is not None:
        check_number("max_grad_norm", cfg.max_grad_norm, 0.0, open_low=True)
    check_number("loss.std_floor", cfg.loss.std_floor, 0.0, 1.0, open_low=True)
    _flag("translation_invariant", cfg.translation_invariant)
    _validate_model(cfg.model)
    _validate_data(cfg.data)


# ---------------------------------------------------------------- building the parts


def make_dataset(cfg: DictConfig) -> MocapDataset:
    """The mocap dataset the data config describes (loaded from ``dataset_dir`` if set)."""
    if cfg.dataset_dir is not None:
        log.info(
            "loading the dataset saved in %s (the clip and filter settings are not used)",
            cfg.dataset_dir,
        )
        dataset = load_dataset(cfg.dataset_dir)
    else:
        dataset = build_dataset(
            clips=_clip_names("data.clips", cfg.clips),
            val_clips=_clip_names("data.val_clips", cfg.val_clips, allow_empty=True),
            folders=list(cfg.folders),
            cache_dir=cfg.cache_dir,
            download=cfg.download,
            settings=FilterSettings(
                cutoff_hz=cfg.filter.cutoff_hz,
                order=cfg.filter.order,
                edge_trim_s=cfg.filter.edge_trim_s,
            ),
            samples_per_clip=cfg.samples_per_clip,
            val_time_fraction=cfg.split.val_time_fraction,
            gap_s=cfg.split.gap_s,
            glitch_deg=cfg.glitch.deg,
            glitch_pad_s=cfg.glitch.pad_s,
            passive=cfg.passive,
            seed=cfg.split.seed,
            torques=cfg.torques,
            tracking=TrackingSettings(
                omega=cfg.pd.omega,
                zeta=cfg.pd.zeta,
                gains=cfg.pd.gains,
                feedforward=cfg.pd.feedforward,
            ),
            skip_bad_clips=cfg.skip_bad_clips,
        )
    check_finite(dataset.data, f"the mocap dataset ({len(dataset)} samples)")
    return dataset


def build_inverse_model(
    cfg: DictConfig,
    layout: JointLayout,
    std_floor: float,
    translation_invariant: bool = False,
    dof_parents: Sequence[int] | None = None,
    armature: Sequence[float] | None = None,
) -> InverseDynamicsModel:
    """The inverse-dynamics model named by ``cfg.name``. `translation_invariant`: no model
    sees the root's position (DeLaN keeps gravity's exact w z potential in its height).
    `dof_parents`: the kinematic tree, for DeLaN's ``model.tree_sparse``. `armature`: the
    model's ``dof_armature``, for DeLaN's ``model.armature``."""
    root_height = not translation_invariant
    if cfg.name == "delan":
        structure = Structure(
            hidden=cfg.hidden,
            layers=cfg.layers,
            activation=cfg.activation,
            diag_shift=cfg.diag_shift,
            dissipation=cfg.dissipation,
            coulomb=cfg.coulomb,
            translation_invariant=translation_invariant,
            still_first_order=cfg.still_first_order,
            dof_parents=dof_parents if cfg.tree_sparse else None,
            armature=armature if cfg.get("armature", False) else None,
        )
        return DeLaNInverse(layout, structure, std_floor=std_floor)
    if cfg.name == "mlp":
        return MLPInverse(
            layout,
            hidden=cfg.hidden,
            activation=cfg.activation,
            std_floor=std_floor,
            root_height=root_height,
        )
    return MLPEnsembleInverse(
        layout,
        ensemble_size=cfg.ensemble_size,
        hidden=cfg.hidden,
        activation=cfg.activation,
        std_floor=std_floor,
        root_height=root_height,
    )


def _mujoco_model(provenance: dict[str, Any]) -> mujoco.MjModel:
    """The model the data were retargeted onto (from their provenance, else humanoid_CMU)."""
    xml = provenance.get("model", {}).get("xml")
    path = Path(xml) if xml and Path(xml).is_file() else humanoid_cmu_xml()
    return mujoco.MjModel.from_xml_path(str(path))


def _tensors(td: TensorDictBase, device: torch.device, dtype: torch.dtype) -> TensorDict:
    """Only q, qd, qdd, tau, on the device in the training dtype. (N,)"""
    return td.select(keys.Q, keys.QD, keys.QDD, keys.TAU).to(device=device, dtype=dtype)


# ---------------------------------------------------------------- the run


def run(cfg: DictConfig, run_dir: Path) -> dict[str, Any]:
    """Validate, build, train and evaluate; write everything into ``run_dir``. The summary."""
    validate_fit_config(cfg)
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    device, dtype = check_device(cfg.device), DTYPES[cfg.dtype]
    run_dir.mkdir(parents=True, exist_ok=True)
    OmegaConf.save(cfg, run_dir / RUN_CONFIG, resolve=True)
    start = time.perf_counter()
    dataset = make_dataset(cfg.data)
    (run_dir / PROVENANCE_FILE).write_text(json.dumps(dataset.provenance, indent=1))
    parts = split_dataset(dataset)
    splits = {name: _tensors(getattr(parts, name), device, dtype) for name in SPLITS}
    clip_ids = {name: getattr(parts, name)[keys.CLIP].reshape(-1) for name in SPLITS}  # (N,)
    mj_model = _mujoco_model(dataset.provenance)
    model = build_inverse_model(
        cfg.model,
        joint_layout(mj_model),
        cfg.loss.std_floor,
        cfg.translation_invariant,
        mj_model.dof_parentid.tolist(),
        mj_model.dof_armature.tolist(),
    )
    model = model.to(device=device, dtype=dtype)
    if cfg.model.get("compile_fit", False):
        compile_fit(model)
    container = OmegaConf.to_container(cfg, resolve=True)
    logger = cfg.logger
    with Recorder(run_dir, logger.wandb, logger.project, logger.group, container) as recorder:
        results = _train(cfg, model, splits, recorder, device)
        summary = _summary(cfg, dataset, model, mj_model, splits, results)
        for name, part in summary["final"].items():  # the evaluated (non-empty) splits
            part["clips"] = _clip_errors(
                model,
                splits[name],
                clip_ids[name],
                dataset.provenance["clips"],
                cfg.eval_batch_size,
            )
        summary["wall_time_s"] = time.perf_counter() - start
        recorder.write_summary(summary)
    _save_model_and_curves(cfg, model, run_dir)
    _log_summary(run_dir, summary)
    return summary


def _train(
    cfg: DictConfig,
    model: InverseDynamicsModel,
    splits: dict[str, TensorDict],
    recorder: Recorder,
    device: torch.device,
) -> list[EpochResult]:
    """Adam on the training split; every non-empty split evaluated and logged per epoch."""
    optimizer = torch.optim.Adam(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    settings = InverseFitSettings(
        epochs=cfg.epochs,
        batch_size=cfg.batch_size,
        eval_batch_size=cfg.eval_batch_size,
        max_grad_norm=cfg.max_grad_norm,
        eval_every=cfg.eval_every,
    )
    generator = torch.Generator(device=device).manual_seed(cfg.seed)
    evaluated = {k: v for k, v in splits.items() if v.shape[0] > 0}
    scheduler = None
    if cfg.lr_schedule == "cosine":  # from lr down to 0 over the epochs
        scheduler = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, T_max=cfg.epochs)

    def on_epoch(result: EpochResult) -> None:
        recorder.log(result.record(), result.epoch)

    return fit_inverse_model(
        model, optimizer, splits["train"], evaluated, settings, generator, on_epoch, scheduler
    )


def _save_model_and_curves(cfg: DictConfig, model: InverseDynamicsModel, run_dir: Path) -> None:
    """``model.pt`` (state dict) and ``loss_curves.png`` from ``metrics.jsonl``."""
    from mbrl_delan.training.fit_plots import LOSS_CURVES_PNG, plot_loss_curves  # matplotlib

    torch.save({"model": cfg.model.name, "state_dict": model.state_dict()}, run_dir / MODEL_FILE)
    records = read_metrics(run_dir / METRICS_FILE)
    plot_loss_curves({cfg.model.name: records}, run_dir / LOSS_CURVES_PNG)


def _split_summary(errors: TorqueErrors, groups: dict[str, tuple[int, ...]]) -> dict[str, Any]:
    joints = [i for name, dofs in groups.items() if name != "root" for i in dofs]
    return {
        "n": errors.n,
        "mse": errors.mse,
        "mse_si": errors.mse_si,
        "r2": errors.r2,
        "joint_mse_si": errors.group(joints).mse_si,
        "groups": {name: errors.group(dofs).as_dict() for name, dofs in groups.items()},
    }


def _clip_errors(
    model: InverseDynamicsModel,
    data: TensorDict,
    clip_ids: Tensor,
    clip_names: list[str],
    batch_size: int,
) -> dict[str, dict[str, float]]:
    """The errors on each clip's samples of one split: n, mse, mse_si, r2 (R^2 against the
    clip's own torque variance). data (N,), clip_ids (N,) indices into `clip_names`."""
    out = {}
    for clip in clip_ids.unique().tolist():
        mask = (clip_ids == clip).to(data.device)
        errors = evaluate_torques(model, data[mask], batch_size)
        out[clip_names[clip]] = {
            "n": errors.n,
            "mse": errors.mse,
            "mse_si": errors.mse_si,
            "r2": errors.r2,
        }
    return out


def _summary(
    cfg: DictConfig,
    dataset: MocapDataset,
    model: InverseDynamicsModel,
    mj_model: mujoco.MjModel,
    splits: dict[str, TensorDict],
    results: list[EpochResult],
) -> dict[str, Any]:
    groups = dof_groups(mj_model)
    final = results[-1].errors
    summary: dict[str, Any] = {
        "data": cfg.data.name,
        "model": cfg.model.name,
        "seed": cfg.seed,
        "device": cfg.device,
        "dtype": cfg.dtype,
        "epochs": len(results),
        "n_parameters": sum(p.numel() for p in model.parameters()),
        "clips": list(dataset.provenance.get("clips", [])),
        "val_clips": list(dataset.provenance.get("split", {}).get("val_clips", [])),
        "skipped_clips": dict(dataset.provenance.get("skipped_clips", {})),
        "torques": dataset.provenance.get("torques", {}).get("source", "inverse"),
        "samples": {name: int(td.shape[0]) for name, td in splits.items()},
        "tau": TAU_DEFINITION,
        "loss": f"per-DoF normalised torque MSE, std floored at {cfg.loss.std_floor} x the largest",
        "dof_groups": {name: len(dofs) for name, dofs in groups.items()},
        "final": {name: _split_summary(err, groups) for name, err in final.items()},
    }
    for name, err in final.items():
        summary[f"{name}_mse"] = err.mse
        summary[f"{name}_mse_si"] = err.mse_si
        summary[f"{name}_r2"] = err.r2
    if isinstance(model, DeLaNInverse):
        q_all = torch.cat([td[keys.Q] for td in splits.values()])
        check = check_mass_matrix(model, q_all, cfg.eval_batch_size)
        summary["mass_matrix"] = check.as_dict()
        summary["positive_definite_fraction"] = check.positive_definite_fraction
        poses = random_poses(mj_model, RANDOM_POSES).to(q_all)  # off the data
        summary["mass_matrix_random_poses"] = check_mass_matrix(model, poses).as_dict()
    return summary


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
    log.info("wall time %.1f s", s["wall_time_s"])


@hydra.main(version_base="1.3", config_path="../configs/fit", config_name="config")
def hydra_main(cfg: DictConfig) -> float | None:
    run_dir = Path(HydraConfig.get().runtime.output_dir)
    try:
        refuse_used_run_dir(run_dir, RUN_FILES, "start the new fit in another hydra.run.dir")
        summary = run(cfg, run_dir)
    except ConfigError as err:
        log.error("config error: %s", err)
        sys.exit(2)
    except (ClipNotFoundError, FileNotFoundError) as err:
        log.error("data not found: %s", err)
        sys.exit(2)
    except (NonFiniteDataError, MocapFormatError, TrackingUnstableError) as err:
        log.error("bad data: %s", err)
        sys.exit(1)
    except TrainingDivergedError as err:
        log.error("training diverged: %s", err)
        sys.exit(1)
    return summary.get("val_clip_mse")


def main() -> float | None:
    """``python -m mbrl_delan.fit``: a config error, Hydra's included, exits 2 naming it."""
    return exit_on_config_errors(hydra_main)


if __name__ == "__main__":
    main()


# ---------------------------------------------------------------- reading a finished run


def read_fit_run(run_dir: str | Path) -> tuple[DictConfig, dict[str, torch.Tensor]]:
    """A finished fit's resolved config and its model's state dict (on the CPU).

    Raises FileNotFoundError naming a missing ``config.yaml`` or ``model.pt`` and ValueError
    for a file that is not what `run` writes."""
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


def load_fit_model(run_dir: str | Path) -> tuple[DictConfig, InverseDynamicsModel]:
    """A finished fit's config and its trained model (on the CPU, float32), built on the
    MuJoCo model its data were retargeted onto (its tree and armature)."""
    cfg, state = read_fit_run(run_dir)
    provenance = Path(run_dir) / PROVENANCE_FILE
    mj_model = _mujoco_model(json.loads(provenance.read_text()) if provenance.is_file() else {})
    model = build_inverse_model(
        cfg.model,
        joint_layout(mj_model),
        cfg.loss.std_floor,
        cfg.get("translation_invariant", False),
        mj_model.dof_parentid.tolist(),
        mj_model.dof_armature.tolist(),
    )
    model.load_state_dict(state)
    return cfg, model
