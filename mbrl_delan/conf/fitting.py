"""The fit of an inverse-dynamics model from its config (`python -m mbrl_delan.fit`'s engine):
the config's checks, the dataset (motion capture, a robot's arrays, simulated excitation), the
model on its system, the training and evaluation that write the run dir, reading a finished
fit, and the Python API `fit_inverse_dynamics`. Benchmarks, `runs` and `evaluate` fit and read
fits through here, as the entry point does."""

from __future__ import annotations

import json
import logging
import pickle
import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, ListConfig, OmegaConf, open_dict
from omegaconf.errors import OmegaConfBaseException
from tensordict import TensorDict, TensorDictBase

from mbrl_delan import keys
from mbrl_delan.accelerate.compile import compile_fit
from mbrl_delan.conf.checks import (
    CONFIGS,
    DTYPES,
    ConfigError,
    check_device,
    check_ranges,
    compose_config,
    load_config_plugins,
    refuse_used_run_dir,
    schema_error_message,
)
from mbrl_delan.conf.fit_schema import DATA_SCHEMAS, FitRunConfig
from mbrl_delan.conf.inverse import (
    InverseContext,
    build_inverse_model,
    check_residual_start,
    typed_model,
)
from mbrl_delan.data.arrays import SPLITS as ARRAY_SPLITS
from mbrl_delan.data.arrays import DerivativeSettings, save_arrays
from mbrl_delan.data.buffer import check_finite
from mbrl_delan.data.excitation import (
    EXCITATION_FORMAT,
    ExcitationSettings,
    excitation_arrays,
    mass_matrix_error,
)
from mbrl_delan.data.inverse_data import (
    FitSystem,
    InverseData,
    array_inverse_data,
    fields_inverse_data,
    mocap_inverse_data,
)
from mbrl_delan.data.mocap import (
    FilterSettings,
    MocapDataset,
    TrackingSettings,
    build_dataset,
    load_dataset,
    random_poses,
)
from mbrl_delan.models.inverse import (
    DeLaNInverse,
    InverseDynamicsModel,
)
from mbrl_delan.models.rigid_body import WhiteBoxInverse
from mbrl_delan.provenance import provenance
from mbrl_delan.registry import (
    INVERSE_MODELS,
)
from mbrl_delan.systems.arms import ARMS, FRICTION_KINDS, arm, friction_kind
from mbrl_delan.systems.system import HINGE
from mbrl_delan.training.identified import (
    IDENTIFIED_FILE,
    identified_numbers,
    identified_summary,
    identified_xml,
)
from mbrl_delan.training.inverse_fit import (
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

# ${stem:${data.robot}} in run-dir names: a shipped arm's name, or an MJCF file's stem
OmegaConf.register_new_resolver("stem", lambda value: Path(str(value)).stem, replace=True)


DATA_NAMES = ("cmu_mocap", "arrays", "excitation")


PROVENANCE_FILE = "dataset_provenance.json"


RANDOM_POSES = 1024  # poses over the whole joint space where the summary checks a DeLaN's M


MODEL_FILE = "model.pt"


# what a fit writes into its run dir; a new fit refuses a folder holding any of them
RUN_FILES = (RUN_CONFIG, PROVENANCE_FILE, MODEL_FILE, METRICS_FILE, SUMMARY_FILE)


FIT_CONFIG_DIR = CONFIGS / "fit"  # this entry point's YAML files


TAU_DEFINITION = {
    "cmu_mocap": "all nv generalized forces (humanoid_CMU: 62 = 6 root residual [world-frame "
    "force, body-frame torque] + 56 hinge torques), the dataset's tau",
    "arrays": "the file's tau: all nv generalized forces applied",
    "excitation": "the motors' torques (MuJoCo's inverse dynamics, joint friction included) "
    "with measurement noise",
}


def _choice(path: str, value: Any, choices: Sequence[str]) -> None:
    if value not in choices:
        raise ConfigError(f"{path}={value!r} is not valid; choose one of: {', '.join(choices)}")


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


def typed_fit_config(cfg: DictConfig) -> DictConfig:
    """`cfg` merged into `FitRunConfig`, its data group into its name's schema
    (`DATA_SCHEMAS`) and its model group into the model's (`typed_model`): a wrong type or an
    unknown key is a ConfigError naming it."""
    _choice("data.name", cfg.data.get("name"), DATA_NAMES)
    _choice("model.name", cfg.model.get("name"), INVERSE_MODELS.names())
    base = OmegaConf.structured(FitRunConfig)
    with open_dict(base):
        base.data = OmegaConf.structured(DATA_SCHEMAS[cfg.data.name])
        base.model = {}
    try:
        typed = OmegaConf.merge(base, cfg)
    except OmegaConfBaseException as err:
        raise ConfigError(schema_error_message(err)) from err
    with open_dict(typed):
        typed.model = typed_model(cfg.model)
    return typed


def validate_fit_config(cfg: DictConfig) -> None:
    """Every value the fit entry point uses, checked before anything is built or written,
    once the config's ``plugins`` are loaded (their inverse-dynamics models): each typed by
    its schema and within its range (`typed_fit_config`, `check_ranges`), then the rules
    between keys (`_check_fit_rules`)."""
    load_config_plugins(cfg)
    typed = typed_fit_config(cfg)
    check_ranges(typed)
    check_device(typed.device)
    _check_fit_rules(typed)


def _check_fit_rules(cfg: DictConfig) -> None:
    """The rules between the fit's keys, and the values a schema cannot type (the data's
    friction flag or kind, ``coulomb_lead``'s auto, clip names that must be strings)."""
    if cfg.stop_on is not None:
        _choice("stop_on", cfg.stop_on, _split_names(cfg.data))
    if cfg.coulomb_lead not in (True, False, "auto"):
        raise ConfigError(
            f"coulomb_lead={cfg.coulomb_lead!r} is not valid; it must be true, false or auto"
        )
    if "start_level" in cfg.model and "diag_shift" in cfg.model:
        check_residual_start(cfg.model)
    DATA_CHECKS[cfg.data.name](cfg.data)
    tree_models = ("white_box", "tree_delan")
    if cfg.model.name in tree_models and cfg.data.name == "arrays" and cfg.data.mjcf is None:
        raise ConfigError(
            f"model={cfg.model.name} needs the robot's kinematic tree: give data.mjcf=MODEL.xml"
        )
    if cfg.model.name in tree_models and cfg.data.name == "cmu_mocap":
        raise ConfigError(
            f"model={cfg.model.name} fits arms (data=excitation or data=arrays data.mjcf=...)"
        )


def _check_arrays(cfg: DictConfig) -> None:
    if not cfg.path:
        raise ConfigError(f"data.path={cfg.path!r} is not valid; give the data file (npz/pt/csv)")
    if cfg.test_path is not None and not Path(cfg.test_path).is_file():
        raise ConfigError(f"data.test_path={cfg.test_path!r}: no such file")
    if (cfg.joints is None) == (cfg.mjcf is None):
        raise ConfigError(
            f"data.joints={cfg.joints!r}, data.mjcf={cfg.mjcf!r}: give one of them (the joint "
            "types as a list, data.joints=[hinge,hinge,slide], or an MJCF file)"
        )
    if cfg.joints is not None and not cfg.joints:
        raise ConfigError("data.joints=[] is not valid; give a list of types")


def _check_excitation(cfg: DictConfig) -> None:
    if cfg.robot not in ARMS and not cfg.robot.endswith(".xml"):
        raise ConfigError(f"data.robot={cfg.robot!r} is not valid; choose one of: "
                          f"{', '.join(ARMS)}, or give an MJCF file (.xml)")  # fmt: skip
    if not isinstance(cfg.friction, bool):
        _choice("data.friction", cfg.friction, FRICTION_KINDS)
    if cfg.test_seed is not None and cfg.test_seed == cfg.seed:
        raise ConfigError(f"data.test_seed={cfg.test_seed}: the training data's own seed")
    given = cfg.get("model_mjcf", "exact")
    if given not in ("exact", "cad") and not (given.endswith(".xml") and Path(given).is_file()):
        raise ConfigError(f"data.model_mjcf={given!r} is not valid; give exact, cad or an "
                          "existing MJCF file (.xml)")  # fmt: skip
    if cfg.cutoff_hz is not None and cfg.cutoff_hz > cfg.rate_hz / 2:
        raise ConfigError(
            f"data.cutoff_hz={cfg.cutoff_hz} is not valid; it must be <= data.rate_hz / 2 "
            f"= {cfg.rate_hz / 2}"
        )


def _check_mocap(cfg: DictConfig) -> None:
    if cfg.dataset_dir is not None:
        return
    clips = _clip_names("data.clips", cfg.clips)
    val = _clip_names("data.val_clips", cfg.val_clips, allow_empty=True)
    test = _clip_names("data.test_clips", cfg.test_clips, allow_empty=True)
    for name, held in (("val_clips", val), ("test_clips", test)):
        unknown = [c for c in held if c not in clips]
        if unknown:
            raise ConfigError(
                f"data.{name}={held} is not valid: {unknown} not in data.clips={clips}"
            )
    if set(val) & set(test):
        raise ConfigError(
            f"data.test_clips={test} is not valid: {sorted(set(val) & set(test))} "
            "also in data.val_clips"
        )
    if len(set(clips)) != len(clips):
        raise ConfigError(f"data.clips={clips} is not valid: a clip is listed twice")


# each data group's rules between its keys (`_check_fit_rules`), beside its schema's types
DATA_CHECKS = {"arrays": _check_arrays, "excitation": _check_excitation, "cmu_mocap": _check_mocap}


def _split_names(data: DictConfig) -> tuple[str, ...]:
    """The splits a data config gives (`InverseData.splits`)."""
    if data.name in ("arrays", "excitation"):
        return ARRAY_SPLITS
    return ("train", "val_time", "val_clip", *(("test",) if data.get("test_clips") else ()))


def make_dataset(cfg: DictConfig) -> MocapDataset:
    """The mocap dataset the data config describes (loaded from ``dataset_dir`` if set)."""
    if cfg.dataset_dir is not None:
        log.info(
            "loading the dataset saved in %s (the clip and filter settings are not used)",
            cfg.dataset_dir,
        )
        dataset = load_dataset(cfg.dataset_dir)
    else:
        held_out = [*cfg.val_clips, *cfg.get("test_clips", [])]
        dataset = build_dataset(
            clips=_clip_names("data.clips", cfg.clips),
            val_clips=_clip_names("data.val_clips", held_out, allow_empty=True),
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


def make_inverse_data(cfg: DictConfig) -> InverseData:
    """The splits the data config describes: the mocap dataset or a logged-arrays file."""
    if cfg.name == "arrays":
        return array_inverse_data(
            cfg.path,
            FitSystem.of(cfg.mjcf if cfg.mjcf is not None else list(cfg.joints)),
            derivative=DerivativeSettings(cutoff_hz=cfg.filter.cutoff_hz, order=cfg.filter.order),
            val_fraction=cfg.split.val_fraction,
            test_fraction=cfg.split.test_fraction,
            seed=cfg.split.seed,
            val_by=cfg.split.val_by,
            test_path=cfg.get("test_path"),
        )
    if cfg.name == "excitation":
        return excitation_inverse_data(cfg)
    dataset = make_dataset(cfg)
    try:
        return mocap_inverse_data(dataset, list(cfg.get("test_clips", [])))
    except ValueError as err:  # test clips that a saved dataset does not hold out
        raise ConfigError(f"data.test_clips: {err}") from err


def excitation_settings(cfg: DictConfig, design: str | None = None) -> ExcitationSettings:
    """`data=excitation`'s trajectory and measurement settings (`design`: another design)."""
    return ExcitationSettings(
        samples=cfg.samples, period_s=cfg.period_s, harmonics=cfg.harmonics,
        rate_hz=cfg.rate_hz, use=cfg.use, q_noise=cfg.q_noise, tau_noise=cfg.tau_noise,
        cutoff_hz=cfg.cutoff_hz, design=design or cfg.get("design", "fourier"),
        centres=cfg.get("centres", "middle"), max_velocity=cfg.get("max_velocity"),
    )  # fmt: skip


def excitation_test_seed(cfg: DictConfig) -> int | None:
    """The seed of `data=excitation`'s own test trajectories: ``data.test_seed``, else
    ``data.seed + 1`` when ``data.test_design`` is set; None: the test split is drawn from
    the training data's trajectories."""
    if cfg.get("test_seed") is not None:
        return int(cfg.test_seed)
    return int(cfg.seed) + 1 if cfg.get("test_design") is not None else None


def excitation_inverse_data(cfg: DictConfig) -> InverseData:
    """An arm's excitation data (`mbrl_delan.data.excitation`; a shipped arm or an MJCF
    file), fitted on the arm's frictionless MJCF (its tree; no armature: the fit learns what
    the motors drive). With ``data.test_seed`` or ``data.test_design`` the test split is
    trajectories of their own (`excitation_test_seed`, the test design), test_fraction x
    samples of them."""
    settings = excitation_settings(cfg)
    friction = friction_kind(cfg.friction)
    if cfg.robot not in ARMS and not Path(cfg.robot).is_file():
        raise ConfigError(f"data.robot={cfg.robot!r}: no such MJCF file")
    structure = cfg.get("structure", "none")
    try:
        fields = excitation_arrays(cfg.robot, friction, settings, cfg.seed, structure)
    except ValueError as err:  # a user MJCF that is not an arm, or without torque limits
        raise ConfigError(f"data.robot={cfg.robot}: {err}") from err
    test_seed = excitation_test_seed(cfg)
    test_design = cfg.get("test_design") or settings.design
    source = {"format": EXCITATION_FORMAT, "robot": cfg.robot, "friction": friction,
              "structure": structure, "model_mjcf": cfg.get("model_mjcf", "exact"),
              "seed": cfg.seed, "test_seed": test_seed, "settings": asdict(settings),
              "test_design": test_design}  # fmt: skip
    test = None
    if test_seed is not None:
        size = excitation_settings(cfg, test_design)
        size = replace(size, samples=max(1, round(cfg.samples * cfg.split.test_fraction)))
        test = (f"excitation test data of {cfg.robot} ({test_design})",
                excitation_arrays(cfg.robot, friction, size, test_seed, structure))  # fmt: skip
    return fields_inverse_data(
        f"excitation data of {cfg.robot}", fields, model_system(cfg), source,
        val_fraction=cfg.split.val_fraction, test_fraction=cfg.split.test_fraction,
        seed=cfg.split.seed, val_by=cfg.split.val_by, test=test,
    )  # fmt: skip


def model_system(cfg: DictConfig) -> FitSystem:
    """The system `data=excitation`'s models are given (``data.model_mjcf``): the arm's own
    MJCF, its CAD file (`FitSystem.of_cad`, drawn from ``cad_seed``, else ``data.seed``) or
    a user's file, which must have the arm's joints."""
    given = cfg.get("model_mjcf", "exact")
    if given == "exact":
        return FitSystem.of(arm(cfg.robot).asset)
    if given == "cad":
        seed = cfg.seed if cfg.get("cad_seed") is None else cfg.cad_seed
        return FitSystem.of_cad(cfg.robot, int(seed))
    try:
        system = FitSystem.of(given)
    except ValueError as err:  # MuJoCo's parse error
        raise ConfigError(f"data.model_mjcf={given}: not a valid MJCF file ({err})") from err
    own = FitSystem.of(arm(cfg.robot).asset).layout
    if system.layout.types != own.types:
        raise ConfigError(
            f"data.model_mjcf={given}: joints {list(system.layout.types)} are not "
            f"data.robot={cfg.robot}'s {list(own.types)}"
        )
    return system


def build_system_model(cfg: DictConfig, system: FitSystem) -> InverseDynamicsModel:
    """`build_inverse_model` of a fit config (``model``, ``loss``, ``translation_invariant``,
    ``periodic_hinges``, ``friction_init``, ``coulomb``, ``coulomb_lead``) for a system."""
    layout = system.layout
    if cfg.get("periodic_hinges", False):  # every hinge's features (sin q, cos q)
        hinges = [t == HINGE for t in layout.types]
        layout = replace(
            layout,
            limited=tuple(lim and not h for lim, h in zip(layout.limited, hinges, strict=True)),
        )
    context = InverseContext(
        layout,
        cfg.loss.std_floor,
        cfg.get("translation_invariant", False),
        system.dof_parents,
        system.armature,
        system.mj_model,
        cfg.get("friction_init"),
        cfg.get("coulomb"),
        cfg.get("coulomb_lead", False),
        friction_kind(cfg.data.friction) if cfg.data.name == "excitation" else None,
    )
    return build_inverse_model(cfg.model, context)


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
    start = time.perf_counter()
    stamp = provenance("mbrl_delan.fit")  # the command, the code, the host at the start
    data = make_inverse_data(cfg.data)
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
    provenance = data.provenance
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
        "tau": TAU_DEFINITION[cfg.data.name],
        "loss": f"per-DoF normalised torque MSE, std floored at {cfg.loss.std_floor} x the largest",
        "dof_groups": {name: len(dofs) for name, dofs in groups.items()},
        "final": {name: split_summary(err, groups) for name, err in final.items()},
    }
    if cfg.data.name == "cmu_mocap":
        test_clips = list(provenance.get("test_clips", []))
        held_out = provenance.get("split", {}).get("val_clips", [])
        summary |= {
            "clips": list(provenance.get("clips", [])),
            "val_clips": [c for c in held_out if c not in test_clips],
            "test_clips": test_clips,
            "skipped_clips": dict(provenance.get("skipped_clips", {})),
            "torques": provenance.get("torques", {}).get("source", "inverse"),
        }
    else:
        where = {"path": provenance["path"]} if "path" in provenance else {
            k: provenance[k] for k in ("robot", "friction", "structure", "model_mjcf", "seed")
            if k in provenance
        }  # fmt: skip
        summary |= {**where, "trajectories": len(data.group_names),
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
    if cfg.data.name == "excitation" and isinstance(model, DeLaNInverse | WhiteBoxInverse):
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
        out[name] = mass_matrix_error(data.robot, data.friction, q64, mass)
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
    log.info("wall time %.1f s", s["wall_time_s"])


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
