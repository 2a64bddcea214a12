"""Config checking and building, for the entry points only.

Library code takes plain arguments; this module turns a Hydra config into those arguments
and rejects a bad value at start with a message that names it and lists what is valid.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import fields
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf

from mbrl_delan.envs.registry import ENV_NAMES
from mbrl_delan.models.base import WorldModel
from mbrl_delan.models.delan import DeLaN
from mbrl_delan.models.delan_ensemble import DeLaNEnsemble
from mbrl_delan.models.ensemble import GaussianEnsemble
from mbrl_delan.planners.base import SamplingPlanner
from mbrl_delan.planners.cem import CEMPlanner
from mbrl_delan.planners.icem import ICEMPlanner
from mbrl_delan.planners.mppi import MPPIPlanner
from mbrl_delan.systems.system import System
from mbrl_delan.training.fit import FitConfig

MODEL_NAMES = ("delan", "ensemble", "delan_ensemble")
PLANNER_NAMES = ("cem", "icem", "mppi")
ORACLE_PLANNERS = ("same", "ilqr")  # budget.oracle_planner
DTYPES = {"float32": torch.float32, "float64": torch.float64}


class ConfigError(ValueError):
    """A config value is invalid; the message names it and the valid choices."""


def refuse_used_run_dir(run_dir: Path, run_files: Sequence[str], instead: str) -> None:
    """A new run must not start in a folder that holds another run's `run_files` (they would
    be overwritten). Raises ConfigError naming the folder, the files found and `instead`
    (what to do), before the run writes anything. (Hydra itself has by then rewritten its
    record of the launch in ``.hydra/`` and opened the log, which gets the error.)"""
    found = [name for name in run_files if (run_dir / name).exists()]
    if found:
        raise ConfigError(
            f"{run_dir} already holds a run ({', '.join(found)}); {instead} "
            "(those files were left as they were)"
        )


def _choice(path: str, value: Any, choices: tuple[str, ...]) -> None:
    if value not in choices:
        raise ConfigError(f"{path}={value!r} is not valid; choose one of: {', '.join(choices)}")


def check_whole(path: str, value: Any, low: int, optional: bool = False) -> None:
    """A whole number >= low (or null when `optional`), else a `ConfigError` naming it."""
    if optional and value is None:
        return
    if not isinstance(value, int) or isinstance(value, bool) or value < low:
        null = " or null" if optional else ""
        raise ConfigError(
            f"{path}={value!r} is not valid; it must be a whole number >= {low}{null}"
        )


def check_number(
    path: str, value: Any, low: float, high: float = math.inf, open_low: bool = False
) -> None:
    """A finite number in [low, high] ((low, high] with `open_low`), else a `ConfigError`."""
    ok = isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
    if ok:
        ok = (value > low if open_low else value >= low) and value <= high
    if not ok:
        bound = f"> {low}" if open_low else f">= {low}"
        limit = "" if high == math.inf else f" and <= {high}"
        raise ConfigError(f"{path}={value!r} is not valid; it must be a number {bound}{limit}")


def build_fit_config(cfg: DictConfig) -> FitConfig:
    """`FitConfig` from ``cfg.fit``; a bad or unknown key is a `ConfigError` naming it."""
    values = OmegaConf.to_container(cfg.fit)
    assert isinstance(values, dict)
    known = {f.name for f in fields(FitConfig)}
    unknown = sorted(set(values) - known)
    if unknown:
        raise ConfigError(
            f"fit.{unknown[0]} is not a fit setting; known: {', '.join(sorted(known))}"
        )
    try:
        return FitConfig(**values)
    except (TypeError, ValueError) as err:
        raise ConfigError(f"fit settings are not valid: {err}") from err


def check_device(device: str) -> torch.device:
    try:
        dev = torch.device(device)
    except RuntimeError as err:
        raise ConfigError(f"device={device!r} is not valid; use cpu, cuda or cuda:N") from err
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"device={device!r} asked for CUDA, but torch sees no CUDA device here")
    if dev.type not in ("cpu", "cuda"):
        raise ConfigError(f"device={device!r} is not valid; use cpu, cuda or cuda:N")
    return dev


def validate_train_config(cfg: DictConfig) -> None:
    """Every value the training entry point uses, checked before anything is built or written."""
    _choice("env.name", cfg.env.name, ENV_NAMES)
    _choice("model.name", cfg.model.name, MODEL_NAMES)
    _choice("planner.name", cfg.planner.name, PLANNER_NAMES)
    _choice("dtype", cfg.dtype, tuple(DTYPES))
    check_device(cfg.device)
    if cfg.model.get("cuda_graph", False) and not str(cfg.device).startswith("cuda"):
        raise ConfigError(f"model.cuda_graph=true needs device=cuda, got device={cfg.device}")
    for path in (
        "planner.horizon",
        "planner.num_samples",
        "planner.iterations",
        "planner.replan_every",
        "budget.iterations",
        "budget.eval_every",
        "model.particles",
        "buffer.capacity",
        "fit.batch_size",
        "fit.max_epochs",
        "fit.rollout_steps",
    ):
        check_number(path, _get(cfg, path), 1)
    _check_rollout_steps(cfg)
    _check_buffer(cfg)
    build_fit_config(cfg)
    check_whole("seed", cfg.seed, 0)
    check_whole("threads", cfg.threads, 1, optional=True)
    check_whole("model.rollout_threads", cfg.model.get("rollout_threads"), 1, optional=True)
    check_number("model.lr", cfg.model.lr, 0.0, open_low=True)
    check_number("model.weight_decay", cfg.model.weight_decay, 0.0)
    for path in (
        "budget.random_episodes",
        "budget.eval_episodes",
        "budget.final_eval_episodes",
        "budget.oracle_episodes",
    ):
        check_number(path, _get(cfg, path), 0)
    oracle_planner = cfg.budget.get("oracle_planner", "same")
    if oracle_planner not in ORACLE_PLANNERS:
        raise ConfigError(
            f"budget.oracle_planner={oracle_planner!r} is not valid; use one of: "
            + ", ".join(ORACLE_PLANNERS)
        )
    if cfg.budget.random_episodes == 0:
        raise ConfigError("budget.random_episodes=0 is not valid: the first fit needs data (>= 1)")
    if cfg.model.name == "delan":
        check_number("model.velocity_margin", cfg.model.velocity_margin, 1.0)
    if cfg.planner.replan_every > cfg.planner.horizon:
        raise ConfigError(
            f"planner.replan_every={cfg.planner.replan_every} is not valid; it "
            f"must be <= planner.horizon={cfg.planner.horizon}"
        )
    if not 0 < cfg.planner.discount <= 1:
        raise ConfigError(f"planner.discount={cfg.planner.discount} is not valid; use (0, 1]")
    risk = cfg.planner.get("risk", 0.0)
    if not isinstance(risk, int | float) or isinstance(risk, bool) or not math.isfinite(risk):
        raise ConfigError(f"planner.risk={risk!r} is not valid; it must be a finite number")
    if (
        cfg.model.name in ("ensemble", "delan_ensemble")
        and cfg.model.propagation == "tsinf"
        and (cfg.model.particles % cfg.model.ensemble_size)
    ):
        raise ConfigError(
            f"model.particles={cfg.model.particles} is not valid with tsinf: it "
            f"must be a multiple of model.ensemble_size={cfg.model.ensemble_size}"
        )


def _check_buffer(cfg: DictConfig) -> None:
    """buffer.device: auto or a device; a memmap lives on disk (auto or cpu)."""
    buffer = cfg.buffer
    device = str(buffer.get("device", "auto"))
    if device != "auto":
        try:
            check_device(device)
        except ConfigError as err:
            raise ConfigError(f"buffer.{err}; or use buffer.device=auto") from err
        if buffer.memmap and device != "cpu":
            raise ConfigError(
                f"buffer.device={device!r} is not valid with buffer.memmap=true: a memmap "
                "lives on disk (use auto or cpu)"
            )
    fraction = buffer.get("device_fraction", 0.5)
    if not isinstance(fraction, int | float) or isinstance(fraction, bool) or not 0 < fraction <= 1:
        raise ConfigError(f"buffer.device_fraction={fraction!r} is not valid; use (0, 1]")


def _check_rollout_steps(cfg: DictConfig) -> None:
    """fit.rollout_steps > 1 needs a DeLaN (or DeLaN ensemble) with a forward loss term."""
    if cfg.fit.rollout_steps == 1:
        return
    if cfg.model.name not in ("delan", "delan_ensemble"):
        raise ConfigError(
            f"fit.rollout_steps={cfg.fit.rollout_steps} is not valid with model={cfg.model.name}: "
            "only delan and delan_ensemble train on K-step rollouts (use 1)"
        )
    if cfg.model.loss == "inverse":
        raise ConfigError(
            f"fit.rollout_steps={cfg.fit.rollout_steps} is not valid with model.loss=inverse: "
            "a rollout loss needs the forward term (model.loss=forward or both)"
        )


def _get(cfg: DictConfig, path: str) -> Any:
    node: Any = cfg
    for part in path.split("."):
        node = node[part]
    return node


def _delan_arguments(cfg: DictConfig, system: System) -> dict[str, Any]:
    """The constructor arguments a DeLaN and every member of a DeLaN ensemble share."""
    return dict(
        layout=system.layout,
        actuation=system.actuation.float(),
        control_dt=system.control_dt,
        hidden=cfg.hidden,
        layers=cfg.layers,
        activation=cfg.activation,
        diag_shift=cfg.diag_shift,
        integrator=cfg.integrator,
        substeps=cfg.substeps,
        loss=cfg.loss,
        dissipation=cfg.dissipation,
        coulomb=cfg.coulomb,
        velocity_margin=cfg.velocity_margin,
        inertia_scaling=cfg.inertia_scaling,
        diagonal_init=cfg.inertia_scaling,
        translation_invariant=cfg.translation_invariant,
        still_first_order=cfg.still_first_order,
        dof_parents=system.mj_model().dof_parentid.tolist() if cfg.tree_sparse else None,
        armature=system.mj_model().dof_armature.tolist() if cfg.armature else None,
        yaw_invariant=cfg.get("yaw_invariant", False),
    )


def build_model(cfg: DictConfig, system: System) -> WorldModel:
    """The world model named by `cfg.name`, with the system's layout and actuation."""
    if cfg.name == "delan":
        return DeLaN(
            **_delan_arguments(cfg, system),
            compile_step=cfg.compile,
            compile_fit=cfg.get("compile_fit", False),
            residual=cfg.residual,
        )
    if cfg.name == "delan_ensemble":
        return DeLaNEnsemble(
            **_delan_arguments(cfg, system),
            residual=cfg.residual,
            ensemble_size=cfg.ensemble_size,
            propagation=cfg.propagation,
            bootstrap=cfg.bootstrap,
        )
    return GaussianEnsemble(
        layout=system.layout,
        nu=system.nu,
        control_dt=system.control_dt,
        ensemble_size=cfg.ensemble_size,
        hidden=cfg.hidden,
        layers=cfg.layers,
        activation=cfg.activation,
        propagation=cfg.propagation,
    )


def build_planner(cfg: DictConfig, system: System, dtype: torch.dtype) -> SamplingPlanner:
    """CEM, iCEM or MPPI over the system's control range."""
    common = dict(
        horizon=cfg.horizon,
        action_low=system.ctrl_low,
        action_high=system.ctrl_high,
        num_samples=cfg.num_samples,
        iterations=cfg.iterations,
        dtype=dtype,
    )
    if cfg.name == "cem":
        return CEMPlanner(
            num_elites=cfg.num_elites,
            init_std=cfg.init_std,
            min_std=cfg.min_std,
            momentum=cfg.momentum,
            **common,
        )
    if cfg.name == "icem":
        return ICEMPlanner(
            num_elites=cfg.num_elites,
            beta=cfg.beta,
            decay=cfg.decay,
            min_samples=cfg.get("min_samples"),
            keep_elites=cfg.keep_elites,
            init_std=cfg.init_std,
            min_std=cfg.min_std,
            momentum=cfg.momentum,
            return_best=cfg.get("return_best", False),
            **common,
        )
    return MPPIPlanner(
        temperature=cfg.temperature,
        noise_std=cfg.noise_std,
        smoothing=cfg.get("smoothing", 0.0),
        **common,
    )
