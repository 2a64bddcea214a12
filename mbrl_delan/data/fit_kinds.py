"""The fit's data kinds (``python -m mbrl_delan.fit data=NAME``), each registered as a
`mbrl_delan.registry.DataKind` with its schema, its rules and its reader: ``arrays`` (a
robot's logs in a file), ``excitation`` (an arm's simulated excitation data) and
``cmu_mocap`` (the CMU clips retargeted onto humanoid_CMU). A plugin's kind registers the
same way (`mbrl_delan.registry.register_fit_data`)."""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

from omegaconf import MISSING, DictConfig, ListConfig

from mbrl_delan.data.arrays import SPLITS as ARRAY_SPLITS
from mbrl_delan.data.arrays import VAL_BY, DerivativeSettings
from mbrl_delan.data.buffer import check_finite
from mbrl_delan.data.excitation import (
    CENTRES,
    DESIGNS,
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
    GAINS,
    TORQUE_SOURCES,
    FilterSettings,
    MocapDataset,
    TrackingSettings,
    build_dataset,
    load_dataset,
)
from mbrl_delan.registry import DataKind, register_fit_data
from mbrl_delan.rules import ConfigError, check_choice, rule
from mbrl_delan.systems.arms import ARMS, FRICTION_KINDS, STRUCTURES, arm, friction_kind
from mbrl_delan.systems.system import JOINT_TYPES

log = logging.getLogger(__name__)


# --- data=arrays -----------------------------------------------------------------------------


@dataclass
class ArraySplitConfig:
    """``data.split`` of arrays and excitation: whole trajectories (or segments) held out."""

    val_fraction: float = rule(low=0, above=True, high=0.9)
    test_fraction: float = rule(low=0, high=0.9)
    seed: int = rule(low=0)
    val_by: str = rule(choices=VAL_BY)


@dataclass
class ArrayFilterConfig:
    """``data.filter`` of arrays: the low-pass before the derivatives (null: none)."""

    cutoff_hz: float | None = rule(None, low=0, above=True)
    order: int = rule(low=1)


@dataclass
class ArraysDataConfig:
    """``data=arrays``: a robot's logs in a file; ``path`` and one of ``joints`` / ``mjcf``
    (`check_arrays`)."""

    name: str = MISSING
    path: str | None = None
    test_path: str | None = None
    joints: list[str] | None = rule(None, choices=tuple(JOINT_TYPES))
    mjcf: str | None = None
    filter: ArrayFilterConfig = field(default_factory=ArrayFilterConfig)
    split: ArraySplitConfig = field(default_factory=ArraySplitConfig)


def check_arrays(cfg: DictConfig) -> None:
    """``data=arrays``' rules: a data file, an existing test file, the joints or an MJCF."""
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


def read_arrays(cfg: DictConfig) -> InverseData:
    """The splits of a logged-arrays file (`mbrl_delan.data.arrays`)."""
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


def _array_splits(cfg: DictConfig) -> tuple[str, ...]:
    return ARRAY_SPLITS


def _array_summary(provenance: Mapping[str, Any]) -> dict[str, Any]:
    """Where the data came from: the file, or the arm that made them and how."""
    if "path" in provenance:
        return {"path": provenance["path"]}
    named = ("robot", "friction", "structure", "model_mjcf", "seed")
    return {k: provenance[k] for k in named if k in provenance}


def _arrays_tree(cfg: DictConfig) -> str | None:
    if cfg.mjcf is not None:
        return None
    return "needs the robot's kinematic tree: give data.mjcf=MODEL.xml"


register_fit_data(
    "arrays",
    DataKind(
        read=read_arrays,
        check=check_arrays,
        splits=_array_splits,
        tau="the file's tau: all nv generalized forces applied",
        summary=_array_summary,
        no_tree=_arrays_tree,
    ),
    ArraysDataConfig,
)


# --- data=excitation -------------------------------------------------------------------------


@dataclass
class ExcitationDataConfig:
    """``data=excitation``: an arm's excitation data (`data.excitation`); ``robot`` a shipped
    arm or an MJCF file, ``friction`` a kind or a flag, ``cutoff_hz`` below Nyquist,
    ``test_seed`` not ``seed`` (`check_excitation`)."""

    name: str = MISSING
    robot: str = MISSING
    friction: Any = MISSING  # none | frictionloss | coulomb_viscous, or true / false
    structure: str = rule(choices=STRUCTURES)
    model_mjcf: str = MISSING  # exact | cad | an MJCF file (.xml)
    cad_seed: int | None = rule(None, low=0)
    design: str = rule(choices=tuple(DESIGNS))
    centres: str = rule(choices=CENTRES)
    test_design: str | None = rule(None, choices=tuple(DESIGNS))
    max_velocity: float | None = rule(None, low=0, above=True)
    samples: int = rule(low=1)
    test_seed: int | None = rule(None, low=0)
    seed: int = rule(low=0)
    period_s: float = rule(low=0, above=True)
    harmonics: int = rule(low=1)
    rate_hz: float = rule(low=0, above=True)
    use: float = rule(low=0, above=True, high=1)
    q_noise: float = rule(low=0)
    tau_noise: float = rule(low=0)
    cutoff_hz: float | None = rule(None, low=0, above=True)
    split: ArraySplitConfig = field(default_factory=ArraySplitConfig)


def check_excitation(cfg: DictConfig) -> None:
    """``data=excitation``'s rules: a shipped arm or an MJCF, a friction kind or flag, a test
    seed apart from the data's, a model file that exists, a cut-off below Nyquist."""
    if cfg.robot not in ARMS and not cfg.robot.endswith(".xml"):
        raise ConfigError(f"data.robot={cfg.robot!r} is not valid; choose one of: "
                          f"{', '.join(ARMS)}, or give an MJCF file (.xml)")  # fmt: skip
    if not isinstance(cfg.friction, bool):
        check_choice("data.friction", cfg.friction, FRICTION_KINDS)
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


def read_excitation(cfg: DictConfig) -> InverseData:
    """An arm's excitation data (`mbrl_delan.data.excitation`; a shipped arm or an MJCF
    file), fitted on the system ``data.model_mjcf`` gives (`model_system`). With
    ``data.test_seed`` or ``data.test_design`` the test split is trajectories of their own
    (`excitation_test_seed`, the test design), test_fraction x samples of them."""
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


def _arm_tree(cfg: DictConfig) -> None:
    return None  # the arm's MJCF, or the file data.model_mjcf gives


def _excitation_friction(cfg: DictConfig) -> str:
    return friction_kind(cfg.friction)


def _arm_mass_matrix_error(cfg: DictConfig, q: Any, mass: Any) -> float:
    return mass_matrix_error(cfg.robot, cfg.friction, q, mass)


register_fit_data(
    "excitation",
    DataKind(
        read=read_excitation,
        check=check_excitation,
        splits=_array_splits,
        tau="the motors' torques (MuJoCo's inverse dynamics, joint friction included) "
        "with measurement noise",
        summary=_array_summary,
        no_tree=_arm_tree,
        friction=_excitation_friction,
        mass_matrix_error=_arm_mass_matrix_error,
    ),
    ExcitationDataConfig,
)


# --- data=cmu_mocap --------------------------------------------------------------------------


@dataclass
class MocapFilterConfig:
    """``data.filter`` of cmu_mocap: the low-pass of the joint angles (below the 60 Hz
    Nyquist frequency of 120 Hz clips) and the seconds trimmed at each clip's ends."""

    cutoff_hz: float | None = rule(None, low=0, above=True, high=60, below=True)
    order: int = rule(low=1)
    edge_trim_s: float = rule(low=0)


@dataclass
class MocapSplitConfig:
    """``data.split`` of cmu_mocap: the end of each clip held out in time, and a gap."""

    val_time_fraction: float = rule(low=0, high=0.95)
    gap_s: float = rule(low=0)
    seed: int = rule(low=0)


@dataclass
class GlitchConfig:
    """``data.glitch``: a joint jumping more than ``deg`` in a frame is cut, ``pad_s`` about."""

    deg: float = rule(low=0, above=True)
    pad_s: float = rule(low=0)


@dataclass
class PDConfig:
    """``data.pd``: the tracking controller of ``torques=pd``."""

    omega: float = rule(low=0, above=True)
    zeta: float = rule(low=0, above=True)
    gains: str = rule(choices=GAINS)
    feedforward: bool = MISSING


@dataclass
class MocapDataConfig:
    """``data=cmu_mocap``: the CMU clips; the clip lists are names (strings), val and test
    clips among ``clips`` (`check_mocap`)."""

    name: str = MISSING
    clips: list[Any] = MISSING
    val_clips: list[Any] = MISSING
    test_clips: list[Any] = field(default_factory=list)
    folders: list[str] = MISSING
    cache_dir: str | None = None
    download: bool = MISSING
    skip_bad_clips: bool = MISSING
    dataset_dir: str | None = None
    samples_per_clip: int | None = rule(None, low=1)
    filter: MocapFilterConfig = field(default_factory=MocapFilterConfig)
    split: MocapSplitConfig = field(default_factory=MocapSplitConfig)
    glitch: GlitchConfig = field(default_factory=GlitchConfig)
    passive: bool = MISSING
    torques: str = rule(choices=TORQUE_SOURCES)
    pd: PDConfig = field(default_factory=PDConfig)


def clip_names(path: str, value: Any, allow_empty: bool = False) -> list[str]:
    """A config's list of clip names as strings; a ConfigError for anything else."""
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


def check_mocap(cfg: DictConfig) -> None:
    """``data=cmu_mocap``'s rules: clip names, the held-out clips among ``clips``, apart."""
    if cfg.dataset_dir is not None:
        return
    clips = clip_names("data.clips", cfg.clips)
    val = clip_names("data.val_clips", cfg.val_clips, allow_empty=True)
    test = clip_names("data.test_clips", cfg.test_clips, allow_empty=True)
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
            clips=clip_names("data.clips", cfg.clips),
            val_clips=clip_names("data.val_clips", held_out, allow_empty=True),
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


def read_mocap(cfg: DictConfig) -> InverseData:
    """The mocap dataset's splits, its test clips held out as the test split."""
    dataset = make_dataset(cfg)
    try:
        return mocap_inverse_data(dataset, list(cfg.get("test_clips", [])))
    except ValueError as err:  # test clips that a saved dataset does not hold out
        raise ConfigError(f"data.test_clips: {err}") from err


def _mocap_splits(cfg: DictConfig) -> tuple[str, ...]:
    return ("train", "val_time", "val_clip", *(("test",) if cfg.get("test_clips") else ()))


def _mocap_summary(provenance: Mapping[str, Any]) -> dict[str, Any]:
    """The clips fitted, held out and skipped, and where the torques came from."""
    test_clips = list(provenance.get("test_clips", []))
    held_out = provenance.get("split", {}).get("val_clips", [])
    return {
        "clips": list(provenance.get("clips", [])),
        "val_clips": [c for c in held_out if c not in test_clips],
        "test_clips": test_clips,
        "skipped_clips": dict(provenance.get("skipped_clips", {})),
        "torques": provenance.get("torques", {}).get("source", "inverse"),
    }


def _mocap_tree(cfg: DictConfig) -> str:
    return "fits arms (data=excitation or data=arrays data.mjcf=...)"


register_fit_data(
    "cmu_mocap",
    DataKind(
        read=read_mocap,
        check=check_mocap,
        splits=_mocap_splits,
        tau="all nv generalized forces (humanoid_CMU: 62 = 6 root residual [world-frame "
        "force, body-frame torque] + 56 hinge torques), the dataset's tau",
        summary=_mocap_summary,
        no_tree=_mocap_tree,
    ),
    MocapDataConfig,
)
