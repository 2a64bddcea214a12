"""Typed schemas of the fit's config (``python -m mbrl_delan.fit``), as `conf.schema` is the
training config's: the YAML files under ``mbrl_delan/configs/fit`` hold the values, these
dataclasses the types and ranges (`rule`). The data group is typed by the schema registered
with its kind (`mbrl_delan.data.fit_kinds`), the model group by the one registered with the
model (`conf.inverse.typed_model`); the few rules between keys are `conf.fitting`'s."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from omegaconf import MISSING

from mbrl_delan.conf.checks import DTYPES
from mbrl_delan.conf.schema import LoggerConfig
from mbrl_delan.rules import rule

LR_SCHEDULES = ("constant", "cosine", "stages")


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
    min_rel_delta: float = rule(low=0, high=1, below=True)
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
