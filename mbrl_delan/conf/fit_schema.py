"""Typed schemas of the fit's config (``python -m mbrl_delan.fit``), as `conf.schema` is the
training config's: the YAML files under ``mbrl_delan/configs/fit`` hold the values, these
dataclasses the types and ranges (`rule`). The data group is typed by the schema of its name
(`DATA_SCHEMAS`), the model group by the one registered with the model
(`conf.inverse.typed_model`); the few rules between keys are `conf.fitting`'s."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from omegaconf import MISSING

from mbrl_delan.conf.checks import DTYPES
from mbrl_delan.conf.schema import LoggerConfig
from mbrl_delan.data.arrays import VAL_BY
from mbrl_delan.data.excitation import CENTRES, DESIGNS
from mbrl_delan.data.mocap import GAINS, TORQUE_SOURCES
from mbrl_delan.rules import rule
from mbrl_delan.systems.arms import STRUCTURES
from mbrl_delan.systems.system import JOINT_TYPES

LR_SCHEDULES = ("constant", "cosine", "stages")


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
    (`conf.fitting`'s rules)."""

    name: str = MISSING
    path: str | None = None
    test_path: str | None = None
    joints: list[str] | None = rule(None, choices=tuple(JOINT_TYPES))
    mjcf: str | None = None
    filter: ArrayFilterConfig = field(default_factory=ArrayFilterConfig)
    split: ArraySplitConfig = field(default_factory=ArraySplitConfig)


@dataclass
class ExcitationDataConfig:
    """``data=excitation``: an arm's excitation data (`data.excitation`); ``robot`` a shipped
    arm or an MJCF file, ``friction`` a kind or a flag, ``cutoff_hz`` below Nyquist,
    ``test_seed`` not ``seed`` (`conf.fitting`'s rules)."""

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
    clips among ``clips`` (`conf.fitting`'s rules)."""

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


DATA_SCHEMAS: dict[str, type] = {
    "arrays": ArraysDataConfig,
    "excitation": ExcitationDataConfig,
    "cmu_mocap": MocapDataConfig,
}


@dataclass
class StagesConfig:
    """``stages``: `lr_schedule=stages`'s stages of falling lr after a warm-up."""

    count: int = rule(low=1)
    decay: float = rule(low=0, above=True, high=1)
    warmup_steps: int = rule(low=0)


@dataclass
class LossConfig:
    """``loss``: the per-DoF torque-std floor, a share of the largest DoF's std."""

    std_floor: float = rule(low=0, above=True, high=1)


@dataclass
class FitRunConfig:
    """The fit's config; ``data`` and ``model`` are typed by their own schemas (their name's).
    ``stop_on`` names one of the data's splits and ``coulomb_lead`` is true, false or auto
    (`conf.fitting`'s rules)."""

    seed: int = rule(low=0)
    device: str = MISSING
    dtype: str = rule(choices=tuple(DTYPES))
    threads: int | None = rule(None, low=1)
    plugins: list[str] = field(default_factory=list)
    epochs: int = rule(low=1)
    patience: int | None = rule(None, low=1)
    min_delta: float = rule(low=0)
    stop_on: str | None = None
    eval_every: int = rule(low=0)
    batch_size: int = rule(low=1)
    eval_batch_size: int = rule(low=1)
    lr: float = rule(low=0, above=True)
    weight_decay: float = rule(low=0)
    lr_schedule: str = rule(choices=LR_SCHEDULES)
    stages: StagesConfig = field(default_factory=StagesConfig)
    max_grad_norm: float | None = rule(None, low=0, above=True)
    translation_invariant: bool = MISSING
    periodic_hinges: bool = MISSING
    friction_init: float | None = rule(None, low=0, above=True)
    coulomb: bool | None = None
    coulomb_lead: Any = MISSING
    loss: LossConfig = field(default_factory=LossConfig)
    logger: LoggerConfig = field(default_factory=LoggerConfig)
    data: Any = MISSING
    model: Any = MISSING
